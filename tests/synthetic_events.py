"""Synthetic event streams for the codec tests and benchmarks (microsecond grid, vectorised).

Test-only: tests import it as `from synthetic_events import ...` (pytest puts tests/ on
sys.path); bench/bench_codecs.py adds tests/ to sys.path itself.

A stream mixes dense row bursts (one microsecond, one row, one polarity, runs of adjacent
columns, what a sensor sends as EVT 3.0 vectors) with uniformly scattered events.
"""

from __future__ import annotations

import numpy as np

from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE


def synthetic_events(n: int, *, duration_us: int | None = None, width: int = 1280,
                     height: int = 720, burst_fraction: float = 0.5, seed: int = 0,
                     t0_us: int = 0) -> np.ndarray:
    """`n` events sorted by time (ns, whole microseconds) over `duration_us` (default n us)."""
    rng = np.random.default_rng(seed)
    n = int(n)
    duration_us = max(int(duration_us if duration_us is not None else n), 1)
    nb = int(round(n * burst_fraction))
    ns = n - nb
    ts = rng.integers(0, duration_us, ns)
    xs = rng.integers(0, width, ns)
    ys = rng.integers(0, height, ns)
    ps = rng.integers(0, 2, ns)
    if nb:
        lens = rng.integers(2, 40, nb // 2 + 2)
        lens = lens[: int(np.searchsorted(np.cumsum(lens), nb)) + 1]
        lens[-1] -= int(lens.sum()) - nb
        lens = lens[lens > 0]
        k = lens.shape[0]
        owner = np.repeat(np.arange(k), lens)
        first = np.cumsum(lens) - lens
        step = rng.integers(1, 3, nb)                  # adjacent pixels or one gap
        cs = np.cumsum(step)
        xoff = cs - cs[first][owner]
        span = int(xoff.max()) + 1
        bx0 = rng.integers(0, max(width - span, 1), k)
        bt = rng.integers(0, duration_us, k)[owner]
        bx = np.minimum(bx0[owner] + xoff, width - 1)
        by = rng.integers(0, height, k)[owner]
        bp = rng.integers(0, 2, k)[owner]
        ts = np.concatenate([ts, bt])
        xs = np.concatenate([xs, bx])
        ys = np.concatenate([ys, by])
        ps = np.concatenate([ps, bp])
    order = np.argsort(ts, kind="stable")
    out = np.empty(n, EVENT_DTYPE)
    out["t"] = (ts[order] + t0_us) * 1000
    out["x"] = xs[order]
    out["y"] = ys[order]
    out["p"] = np.where(ps[order] > 0, 1, -1)
    return out


def synthetic_triggers(n: int, *, duration_us: int, seed: int = 1, t0_us: int = 0,
                       max_id: int = 16) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.empty(int(n), TRIGGER_DTYPE)
    out["t"] = (np.sort(rng.integers(0, max(duration_us, 1), int(n))) + t0_us) * 1000
    out["id"] = rng.integers(0, max_id, int(n))
    out["value"] = rng.integers(0, 2, int(n))
    return out
