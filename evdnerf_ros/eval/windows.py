"""Which windows an evaluation scores, and their log changes from one render per distinct time.

Evaluation scores every 4th window (``metrics.protocol_windows``) at the trained window count
and 4x / 8x finer.  The edges of the finer counts fall on the coarser ones (``window_edges``
splits with exact integer arithmetic, so edge k of n windows is edge 8k of 8n), so rendering
per distinct time instead of per window end, across counts, saves a render in three (a
Jet-Down set's 208 window ends per view are 160 distinct times).
"""

from __future__ import annotations

from collections import defaultdict
from typing import Callable, Sequence

import numpy as np

from ..events.slicing import window_edges
from .metrics import protocol_windows


def scored_windows(t_start: int, t_end: int, n_windows: int, windows=None) -> tuple[np.ndarray, list[int]]:
    """(edges of ``n_windows`` windows over the span, indices of the windows scored): the
    protocol's unless ``windows`` names them; one window (the first) when it selects none."""
    edges = window_edges(t_start, t_end, n_windows)
    ks = protocol_windows(n_windows) if windows is None else list(windows)
    return edges, [int(k) for k in ks] if len(ks) else [0]


def window_changes(log_image: Callable[[int], np.ndarray],
                   windows: Sequence[tuple[int, int]]) -> list[np.ndarray]:
    """``log_image(t_end) - log_image(t_start)`` of each (t_start, t_end) window, in the given
    order, calling ``log_image`` once per distinct time, in ascending time, and holding only
    the images a window not yet finished still needs."""
    last_use: dict[int, int] = {}
    ending = defaultdict(list)
    for i, (a, b) in enumerate(windows):
        a, b = int(a), int(b)
        last_use[a] = max(last_use.get(a, a), b)
        last_use[b] = max(last_use.get(b, b), b)
        ending[b].append(i)
    out: list = [None] * len(windows)
    live: dict[int, np.ndarray] = {}
    for t in sorted(last_use):
        live[t] = log_image(t)
        for i in ending[t]:
            out[i] = live[t] - live[int(windows[i][0])]
        for u in [u for u in live if last_use[u] <= t]:
            del live[u]
    return out


__all__ = ["scored_windows", "window_changes"]
