"""Time slicing of sorted event arrays by binary search (never a scan)."""

from __future__ import annotations

import numpy as np


def window_indices(t: np.ndarray, t_start, t_end) -> tuple[int, int]:
    """Index range [i0, i1) of the events with t_start <= t < t_end."""
    i0, i1 = np.searchsorted(t, [t_start, t_end], side="left")
    return int(i0), int(max(i0, i1))


def time_slice(events: np.ndarray, t_start: int, t_end: int) -> np.ndarray:
    """Events in the half-open window [t_start, t_end) (a view, no copy)."""
    i0, i1 = window_indices(events["t"], np.int64(t_start), np.int64(t_end))
    return events[i0:i1]


def window_edges(t_start: int, t_end: int, n_windows: int) -> np.ndarray:
    """n_windows + 1 int64 edges splitting [t_start, t_end) as evenly as integers allow."""
    if n_windows < 1:
        raise ValueError(f"n_windows must be >= 1, got {n_windows}")
    t_start, t_end = int(t_start), int(t_end)
    span = t_end - t_start
    if span < n_windows:
        raise ValueError(f"cannot split {span} ns into {n_windows} non-empty windows")
    # Integer arithmetic on Python ints: exact for any int64 span.
    return np.array([t_start + (span * k) // n_windows for k in range(n_windows + 1)], np.int64)


def frame_at_or_before(t, period, frame):
    """The time of the frame at or before ``t`` on the grid ``frame + k * period`` (int64 ns;
    scalars or arrays alike): where a frame-based camera's last render before ``t`` was."""
    return frame + (t - frame) // period * period


def window_of_each_event(t: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Window index per event for sorted edges (-1 before the first edge, K at/after the last)."""
    return np.searchsorted(edges, t, side="right") - 1
