"""Event-rate histograms (events per second in fixed bins) and their plot."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_output
from ..errors import InputError
from ..limits import check_memory


def event_rate(t: np.ndarray, bin_ns: int, t_start: int | None = None,
               t_end: int | None = None, *, name: str = "rate bin") -> tuple[np.ndarray, np.ndarray]:
    """Counts of sorted int64 times in bins of `bin_ns`; returns (edges int64 (K+1,), counts (K,)).

    `name` is the flag that set the bin, named when the bins would not fit in memory.
    """
    bin_ns = int(bin_ns)
    if bin_ns <= 0:
        raise InputError(f"{name} must be a positive number of ns, got {bin_ns}")
    t = np.asarray(t, np.int64)
    if t_start is None:
        t_start = int(t[0]) if t.size else 0
    if t_end is None:
        t_end = int(t[-1]) + 1 if t.size else t_start + bin_ns
    n_bins = max(1, -(-(int(t_end) - int(t_start)) // bin_ns))
    # edges, counts and bincount's working copy: three int64 arrays of n_bins
    check_memory(24.0 * n_bins, f"{name} {bin_ns} ns over {(int(t_end) - int(t_start)) / 1e9:g} s "
                 f"({n_bins} bins)", f"choose a larger {name}")
    edges = int(t_start) + bin_ns * np.arange(n_bins + 1, dtype=np.int64)
    i0, i1 = np.searchsorted(t, [t_start, t_end])
    idx = (t[i0:i1] - np.int64(t_start)) // bin_ns
    return edges, np.bincount(idx, minlength=n_bins)[:n_bins]


def plot_event_rate(path, curves: dict[str, tuple[np.ndarray, np.ndarray]], *,
                    title: str = "event rate", t_origin_ns: int | None = None,
                    overwrite: bool = True) -> Path:
    """Plot one or more (edges, counts) curves as events/s against seconds; atomic PNG write.

    `overwrite` replaces an existing file at `path` (never a folder)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=(8, 3.2))
    for name, (edges, counts) in curves.items():
        origin = int(edges[0]) if t_origin_ns is None else int(t_origin_ns)
        bin_s = (int(edges[1]) - int(edges[0])) * 1e-9
        # Display only: seconds from int64 differences, never from absolute float times.
        centres = ((edges[:-1] - origin) + (edges[1:] - edges[:-1]) // 2) * 1e-9
        ax.step(centres, counts / bin_s, where="mid", label=name, linewidth=1)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("events / s")
    ax.set_title(title)
    if len(curves) > 1:
        ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, overwrite=overwrite)


def save_figure(fig, path, *, overwrite: bool = True) -> Path:
    """Write a matplotlib figure as PNG atomically and close it (also on error).

    `overwrite` replaces an existing *file* only; atomic_output never deletes a folder."""
    import matplotlib.pyplot as plt

    try:
        with atomic_output(path, overwrite=overwrite) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    finally:
        plt.close(fig)
    return Path(path)
