"""Run-to-run agreement of repeated takes of one view (``evdnerf capture --repeats N``).

EvDNeRF needs the motion to repeat: every view must see the same scene at the same time after
the trigger. A real servo drifts (warm-up, load, supply), so the capture can record a view
several times and compare the takes, each on its own clock aligned at its trigger edge (the
firmware's pulse at the motion's first frame; a bag without one is aligned at its servo START
stamp):

- **event-rate curves** (events per ``bin_ns`` bin over the motion span): Pearson correlation
  with the first take, relative L1 difference, the lag (ms) that best aligns them and the
  correlation once aligned — a take whose motion runs early or late shows in the lag, one whose
  motion differs in shape in the aligned correlation;
- **event images** (signed event counts per pixel in ``windows`` equal windows over the span):
  mean Pearson correlation over the windows where the first take has events, and relative L1
  difference — a take whose scene is elsewhere at the same time shows here;
- event counts per take.

A correlation of a curve or image with no variance is undefined and reported as None.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..topics import EVENT_TRIGGERS, EVENTS, SERVO_TRIGGER

#: Largest lag (ms) searched when aligning two rate curves.
MAX_LAG_MS = 50.0


@dataclass
class Take:
    """One take of a view, from its trigger edge: rate curve and event images."""

    name: str
    anchor_ns: int                 # the view-clock time everything is measured from
    anchor: str                    # "trigger" or "START"
    events: int                    # events inside the span
    rate: np.ndarray               # (bins,) int64 events per bin
    images: np.ndarray             # (windows, H, W) int32 signed event counts


def load_take(bag, *, span_ns: int, bin_ns: int = 1_000_000, windows: int = 16, topic: str = EVENTS,
              name: str | None = None) -> Take:
    """Read one take's bag and bin its events from the trigger edge over ``span_ns``."""
    from ..io.rosbag2 import open_bag, read_events
    from .sync import _start_stamp

    bag = Path(bag)
    span_ns, bin_ns, windows = int(span_ns), int(bin_ns), int(windows)
    if span_ns <= 0 or bin_ns <= 0 or windows < 1 or bin_ns > span_ns:
        raise InputError(f"{bag}: repeatability needs span > 0, 0 < bin <= span and windows >= 1 "
                         f"(got span {span_ns} ns, bin {bin_ns} ns, {windows} windows)")
    stream = read_events(bag, topic)
    tr = stream.triggers
    with open_bag(bag) as b:
        start = _start_stamp(b, SERVO_TRIGGER)
        if EVENT_TRIGGERS != topic and EVENT_TRIGGERS in b.topics:      # a libcaer camera's edges
            tr = np.concatenate([tr, read_events(bag, EVENT_TRIGGERS).triggers])
    rising = np.sort(tr["t"][tr["value"] == 1])
    if rising.size:
        anchor_ns, anchor = int(rising[0]), "trigger"
    elif start is not None:
        anchor_ns, anchor = int(start), "START"
    else:
        raise InputError(f"{bag}: no trigger edge and no servo START in the bag: the takes cannot be aligned; "
                         "connect the servo board's trigger output to the camera's trigger input")
    width, height = int(stream.width), int(stream.height)
    ev = stream.events
    dt = ev["t"].astype(np.int64) - np.int64(anchor_ns)
    ev, dt = ev[(dt >= 0) & (dt < span_ns)], dt[(dt >= 0) & (dt < span_ns)]
    bins = -(-span_ns // bin_ns)
    rate = np.bincount(dt // bin_ns, minlength=bins).astype(np.int64)
    w = (dt * windows) // span_ns
    pix = (w * height + ev["y"].astype(np.int64)) * width + ev["x"].astype(np.int64)
    images = np.bincount(pix, weights=ev["p"].astype(np.float64), minlength=windows * height * width)
    return Take(name or bag.name, anchor_ns, anchor, int(ev.size), rate,
                images.reshape(windows, height, width).astype(np.int32))


def _corr(a, b) -> float | None:
    a = np.asarray(a, np.float64).ravel()
    b = np.asarray(b, np.float64).ravel()
    a, b = a - a.mean(), b - b.mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return None if den == 0.0 else float((a * b).sum() / den)


def _rel_l1(ref, other) -> float | None:
    ref = np.asarray(ref, np.float64)
    den = float(np.abs(ref).sum())
    return None if den == 0.0 else float(np.abs(np.asarray(other, np.float64) - ref).sum() / den)


def best_lag_ms(ref: np.ndarray, other: np.ndarray, bin_ns: int, max_lag_ms: float = MAX_LAG_MS) -> float | None:
    """The shift (ms, positive: ``other`` runs late) that best aligns two rate curves."""
    a = np.asarray(ref, np.float64) - np.mean(ref)
    b = np.asarray(other, np.float64) - np.mean(other)
    if not a.any() or not b.any():
        return None
    n = a.size
    lags = np.arange(-min(n - 1, int(max_lag_ms * 1e6 // bin_ns)), min(n - 1, int(max_lag_ms * 1e6 // bin_ns)) + 1)
    score = [float(np.dot(*_overlap(a, b, int(k)))) for k in lags]
    return float(lags[int(np.argmax(score))] * bin_ns / 1e6)


def _overlap(a: np.ndarray, b: np.ndarray, lag: int) -> tuple[np.ndarray, np.ndarray]:
    """The parts of two curves that overlap when ``b`` is moved ``lag`` bins earlier."""
    n = a.size
    return a[max(0, -lag):n - max(0, lag)], b[max(0, lag):n - max(0, -lag)]


def compare_takes(takes: list[Take], bin_ns: int) -> dict:
    """Every take against the first (module docstring); ``worst`` sums up the run-to-run spread."""
    if len(takes) < 2:
        raise InputError("repeatability: compare at least 2 takes of a view")
    ref = takes[0]
    shapes = {t.images.shape for t in takes}
    if len(shapes) > 1:
        raise InputError(f"repeatability: the takes {[t.name for t in takes]} have different sensor sizes or "
                         f"windows {sorted(shapes)}")
    active = [w for w in range(ref.images.shape[0]) if ref.images[w].any()]
    rows = []
    for t in takes[1:]:
        img_corr = [c for c in (_corr(ref.images[w], t.images[w]) for w in active) if c is not None]
        rows.append({"take": t.name, "anchor": t.anchor, "events": t.events,
                     "count_ratio": None if ref.events == 0 else t.events / ref.events,
                     "rate_corr": _corr(ref.rate, t.rate), "rate_rel_l1": _rel_l1(ref.rate, t.rate),
                     "lag_ms": (lag := best_lag_ms(ref.rate, t.rate, bin_ns)),
                     "rate_corr_aligned": None if lag is None else _corr(*_overlap(ref.rate, t.rate,
                                                                                  round(lag * 1e6 / bin_ns))),
                     "image_corr": float(np.mean(img_corr)) if img_corr else None,
                     "image_rel_l1": _rel_l1(ref.images, t.images)})

    def worst(key, pick):
        vals = [r[key] for r in rows if r[key] is not None]
        return pick(vals) if vals else None

    return {"reference": ref.name, "reference_events": ref.events, "anchor": ref.anchor, "bin_ms": bin_ns / 1e6,
            "windows": int(ref.images.shape[0]), "takes": rows,
            "worst": {"rate_corr": worst("rate_corr", min), "rate_corr_aligned": worst("rate_corr_aligned", min),
                      "rate_rel_l1": worst("rate_rel_l1", max),
                      "abs_lag_ms": worst("lag_ms", lambda v: max(abs(x) for x in v)),
                      "image_corr": worst("image_corr", min), "image_rel_l1": worst("image_rel_l1", max)}}


def repeatability(bags, *, span_ns: int, bin_ns: int = 1_000_000, windows: int = 16, topic: str = EVENTS) -> dict:
    """Load the takes in ``bags`` (first: the reference) and compare them."""
    takes = [load_take(b, span_ns=span_ns, bin_ns=bin_ns, windows=windows, topic=topic) for b in bags]
    return compare_takes(takes, bin_ns)


__all__ = ["Take", "load_take", "compare_takes", "repeatability", "best_lag_ms", "MAX_LAG_MS"]
