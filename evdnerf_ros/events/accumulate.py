"""Per-pixel accumulation: signed counts and log-brightness-change images (paper Eq. 4/5).

dL = C+ * N+ - C- * N-  over any window (Eq. 5); the inverse, the minimum event count a
predicted change implies, is floor(dL / C) per polarity (Eq. 4).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .slicing import time_slice, window_of_each_event


def _check_geometry(width: int, height: int) -> None:
    if width <= 0 or height <= 0:
        raise InputError(f"image size must be positive, got {width}x{height}")


def polarity_counts(events: np.ndarray, width: int, height: int) -> np.ndarray:
    """(2, H, W) int64 counts: [0] positive events N+, [1] negative events N-."""
    _check_geometry(width, height)
    flat = events["y"].astype(np.int64) * width + events["x"]
    flat += (events["p"] < 0) * (width * height)
    return np.bincount(flat, minlength=2 * width * height).reshape(2, height, width)


def signed_counts(events: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) int64 net count N+ - N-."""
    _check_geometry(width, height)
    flat = events["y"].astype(np.int64) * width + events["x"]
    return np.bincount(flat, weights=events["p"], minlength=width * height).astype(
        np.int64).reshape(height, width)


def log_change_image(events: np.ndarray, width: int, height: int, c_pos: float, c_neg: float,
                     t_start: int | None = None, t_end: int | None = None) -> np.ndarray:
    """(H, W) float32 dL = C+ N+ - C- N- of the events in [t_start, t_end) (Eq. 5)."""
    _check_thresholds(c_pos, c_neg)
    if t_start is not None or t_end is not None:
        lo = np.iinfo(np.int64).min if t_start is None else t_start
        hi = np.iinfo(np.int64).max if t_end is None else t_end
        events = time_slice(events, lo, hi)
    n = polarity_counts(events, width, height)
    return (c_pos * n[0] - c_neg * n[1]).astype(np.float32)


def log_change_stack(events: np.ndarray, edges: np.ndarray, width: int, height: int,
                     c_pos: float, c_neg: float) -> np.ndarray:
    """(K, H, W) float32 dL images for the K windows [edges[k], edges[k+1]) in one pass."""
    _check_thresholds(c_pos, c_neg)
    _check_geometry(width, height)
    edges = np.asarray(edges, np.int64)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise InputError("window edges must be a strictly increasing 1-D array of >= 2 times")
    k_windows = edges.size - 1
    inside = slice(*np.searchsorted(events["t"], [edges[0], edges[-1]]))
    ev = events[inside]
    k = window_of_each_event(ev["t"], edges)
    pixels = width * height
    # Count per polarity first, then combine: exactly C+ N+ - C- N- whatever the event order.
    flat = (k * pixels + ev["y"].astype(np.int64) * width + ev["x"]) * 2 + (ev["p"] < 0)
    n = np.bincount(flat, minlength=2 * k_windows * pixels).reshape(k_windows, height, width, 2)
    return (c_pos * n[..., 0] - c_neg * n[..., 1]).astype(np.float32)


def counts_from_log_change(d_l: np.ndarray, c_pos: float, c_neg: float) -> np.ndarray:
    """Minimum signed event count implied by a log change (Eq. 4): floor(|dL| / C) per sign."""
    _check_thresholds(c_pos, c_neg)
    d_l = np.asarray(d_l, np.float64)
    pos = np.floor(np.maximum(d_l, 0.0) / c_pos)
    neg = np.floor(np.maximum(-d_l, 0.0) / c_neg)
    return (pos - neg).astype(np.int64)


def _check_thresholds(c_pos: float, c_neg: float) -> None:
    if not (np.isfinite(c_pos) and np.isfinite(c_neg) and c_pos > 0 and c_neg > 0):
        raise InputError(f"contrast thresholds must be finite and > 0, got C+={c_pos}, C-={c_neg}")
