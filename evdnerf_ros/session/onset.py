"""Motion onset on an event-rate curve, and the sub-bin shift between two views' curves:
the algorithms behind ``evdnerf sync``'s ``rate`` and ``onset`` methods (the orchestration
is :mod:`evdnerf_ros.session.sync`; the parameters named below are fields of its
``SyncOptions``).

Event-rate onset, per view
--------------------------
1. *Hot pixels* are removed first: a pixel is hot when its event count is a robust outlier
   (above ``median + hot_k * max(1.4826 MAD, sqrt(median), 1)`` of the active pixels'
   counts) **and** it fires steadily: in at least ``hot_coverage`` of ``hot_slices`` equal
   slices of the recording, with per-slice counts no more dispersed than a Poisson
   process's (variance / mean <= ``hot_dispersion``). A moving edge crosses a pixel at a few
   moments; a hot pixel fires all the time, also before and after the motion. Their number
   is reported.
2. The rate curve: event counts per ``bin_ns`` over the whole recording (bag start to end).
3. *Noise floor*: median and MAD of the ``N``-bin moving sums (``N`` bins = ``sustain_ns``)
   over the lowest-rate stretch of ``quiet_ns``; re-estimated from everything before the
   detected rise. The spread never drops below the Poisson value ``sqrt(max(median, 1))``,
   so a noise-free floor of zeros does not make every single event "significant".
4. *Detection*: the first bin at which ``sustain_windows`` consecutive, disjoint ``N``-bin
   windows all exceed ``floor + k * spread`` (20 ms by default). Short bursts (pre-motion
   jitter, a bump of the table) cover one or two windows and fail this test; later and
   higher peaks are never looked at (the *first* sustained rise is the onset).
5. *Walk back* to where the rise leaves the floor: from the last ``N``-bin window before the
   detection whose sum is still within ``floor + floor_z * spread`` (a burst that the rate
   drops back to the floor after is thus cut off), the change point is the last minimum of
   the drifted cumulative sum ``S(e) = sum_{i<e} clip(c_i - floor - d, -h, h)`` over the next
   two windows, ``h`` the rise's height above the floor and ``d = h / 4``: ``S`` falls in
   the floor and climbs in the rise (the CUSUM change-point estimate, whatever the bin
   size). Finally the onset is placed inside its bin from how full the bin is (a rise that
   starts part-way through a bin fills it partly). ``rate_onset`` is accurate to about a
   bin (at coarse bins) or to the rise's own sharpness (at fine bins).

Sub-bin refinement (``rate``)
-----------------------------
Views see the motion from different angles, so their rate curves differ in height and in
detail; what they share is *when* the motion starts and how its speed evolves. Each view's
onset is re-detected on ``refine_anchor_ns`` bins (1 ms) as the anchor (coarse bins place it
only to a bin, fine bins hold too few events each to place it well); the curves are
histogrammed at ``refine_bin_ns`` (default 100 µs), lightly smoothed, and an anchor-aligned
window of the early motion (``refine_pre_ns`` before to ``refine_post_ns`` after) of each
view is correlated (Pearson, so the gain of each view drops out) with the reference view's
at lags up to ``refine_search_ns``; the peak is interpolated by a parabola through its
neighbours. The refined result therefore does not depend on ``bin_ns``. The search is narrow on purpose: rate curves of a
steady motion have ripples that repeat, and a wide search lets the correlation lock onto
the wrong one. A view's refined origin is its anchor plus the lag when the peak is at least
``min_correlation`` and inside the search range; otherwise the anchor is kept and the view's
``quality.refined`` is false. The reference view's refined origin is its anchor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..events.rate import event_rate

__all__ = ["Floor", "Onset", "correlate_onsets", "detect_onset", "hot_pixels", "smooth"]


def hot_pixels(events: np.ndarray, width: int, height: int, t_start: int, t_end: int, *,
               k: float = 10.0, coverage: float = 0.75, dispersion: float = 2.0, slices: int = 16,
               min_events: int = 20) -> np.ndarray:
    """Flat indices (y * width + x) of pixels that fire at an outlying, steady rate.

    A pixel is hot when (1) its count exceeds ``median + k * max(1.4826 MAD, sqrt(median), 1)``
    of the counts of the pixels that fired at all (and ``min_events``), and (2) it fires
    steadily: it has events in at least ``coverage`` of ``slices`` equal slices of
    [t_start, t_end), and its counts per slice vary no more than a Poisson process's
    (variance / mean <= ``dispersion``; a pixel that a moving edge crosses now and then, with
    noise in between, is far more bursty).
    """
    if events.size == 0:
        return np.empty(0, np.int64)
    n_pix = int(width) * int(height)
    pix = events["y"].astype(np.int64) * int(width) + events["x"]
    counts = np.bincount(pix, minlength=n_pix)
    active = counts[counts > 0]
    med = float(np.median(active))
    mad = 1.4826 * float(np.median(np.abs(active - med)))
    bound = max(med + k * max(mad, math.sqrt(med), 1.0), float(min_events) - 0.5)
    cand = np.flatnonzero(counts > bound)
    if cand.size == 0:
        return cand.astype(np.int64)
    span = max(1, int(t_end) - int(t_start))
    lookup = np.full(n_pix, -1, np.int64)
    lookup[cand] = np.arange(cand.size)
    sel = lookup[pix]
    keep = sel >= 0
    s = ((events["t"][keep] - np.int64(t_start)) * slices // span).clip(0, slices - 1)
    hits = np.bincount(sel[keep] * slices + s, minlength=cand.size * slices).reshape(cand.size, slices)
    covered = (hits > 0).sum(axis=1) / slices
    mean = hits.mean(axis=1)
    disp = hits.var(axis=1, ddof=1) / np.maximum(mean, 1e-12) if slices > 1 else np.zeros(cand.size)
    return cand[(covered >= coverage) & (disp <= dispersion)].astype(np.int64)


@dataclass
class Floor:
    """Noise floor of a rate curve: per-bin level, and N-bin window statistics."""

    per_bin: float
    window_median: float
    window_sigma: float
    threshold: float


@dataclass
class Onset:
    """A detected motion onset on a rate curve (times in the view's clock)."""

    t_ns: int                 # where the rise leaves the floor (placed inside its bin)
    index: int                # the change point's bin edge
    detect_index: int         # first bin of the first sustained window above the threshold
    floor: Floor
    rise_per_bin: float       # mean count per bin over the sustained windows
    snr: float                # mean window excess over the floor in robust sigmas


def _floor(c: np.ndarray, n: int, k: float) -> Floor:
    """Floor from a stretch of counts `c`: statistics of its n-bin moving sums."""
    cs = np.concatenate([[0.0], np.cumsum(c, dtype=np.float64)])
    m = cs[n:] - cs[:-n] if c.size >= n else np.array([cs[-1] * n / max(c.size, 1)])
    med = float(np.median(m))
    mad = 1.4826 * float(np.median(np.abs(m - med)))
    sigma = max(mad, math.sqrt(max(med, 1.0)))
    return Floor(per_bin=med / n, window_median=med, window_sigma=sigma, threshold=med + k * sigma)


def _first_sustained(m: np.ndarray, threshold: float, n: int, windows: int, start: int = 0) -> int | None:
    above = m > threshold
    last = above.size - (windows - 1) * n
    if last <= start:
        return None
    ok = above[start:last].copy()
    for w in range(1, windows):
        ok &= above[start + w * n:last + w * n]
    hit = np.flatnonzero(ok)
    return None if hit.size == 0 else int(start + hit[0])


def _walk_back(c: np.ndarray, floor_per_bin: float, rise_per_bin: float, lo: int, hi: int) -> int:
    """Change point: last minimum over edges [lo, hi] of S(e) = sum_{i<e} (c_i - floor - d), the
    increments clipped to +-(rise - floor) so that a short burst counts like a few rise bins."""
    a = max(rise_per_bin - floor_per_bin, 1e-9)
    x = np.clip(c - (floor_per_bin + 0.25 * a), -a, a)
    s = np.concatenate([[0.0], np.cumsum(x)])
    seg = s[lo:hi + 1]
    return int(lo + seg.size - 1 - np.argmin(seg[::-1]))


def detect_onset(counts: np.ndarray, edges: np.ndarray, *, k: float = 8.0, floor_z: float = 1.5,
                 sustain_bins: int = 4, windows: int = 5, quiet_bins: int = 50) -> tuple[Onset | None, str]:
    """Motion onset on a rate curve; returns (onset, "") or (None, reason)."""
    c = np.asarray(counts, np.float64)
    n = max(1, int(sustain_bins))
    nb = c.size
    if nb < n * (windows + 1):
        return None, (f"the recording is only {nb} bins long; at least {n * (windows + 1)} are "
                      "needed (a quiet lead-in and a sustained rise)")
    if not c.any():
        return None, "the view has no events (after hot-pixel removal)"
    cs = np.concatenate([[0.0], np.cumsum(c)])
    m = cs[n:] - cs[:-n]                        # m[i] = sum of c[i:i+n]
    q = min(max(int(quiet_bins), 2 * n), nb)
    stretch = cs[q:] - cs[:-q]
    j = int(np.argmin(stretch))
    found = _rise(c, m, (j, j + q), n, k, floor_z, windows)
    if found is not None and found[0] - n > q:
        # Re-estimate the floor from everything before the rise (more bins, and the part of
        # the recording that matters), then detect again.
        again = _rise(c, m, (0, found[0] - n), n, k, floor_z, windows)
        found = again if again is not None else found
    if found is None:
        fl = _floor(c[j:j + q], n, k)
        return None, (f"no sustained rise of the event rate: the highest {n}-bin count is {m.max():.0f} "
                      f"events against a threshold of {fl.threshold:.1f} (floor {fl.window_median:.1f} "
                      f"+ {k:g} x {fl.window_sigma:.1f}) held for {windows} windows of {n} bins")
    e_on, i0, fl, rise, snr = found
    if e_on < n:
        return None, ("the event rate is already high at the start of the recording (no quiet "
                      "lead-in before the motion); record from before the motion starts")
    return Onset(t_ns=_interpolate(c, edges, e_on, fl.per_bin, rise), index=e_on, detect_index=i0,
                 floor=fl, rise_per_bin=rise, snr=snr), ""


def _interpolate(c, edges, e_on, floor, rise) -> int:
    """Place the onset inside its bin from how full the bins around the change point are: a
    rise that starts part-way through a bin fills that bin only partly."""
    b = int(edges[1] - edges[0])
    h = rise - floor
    if h <= 0 or e_on >= c.size:
        return int(edges[e_on])
    f1 = min(max((c[e_on] - floor) / h, 0.0), 1.0)
    if f1 < 1.0:                                 # the rise starts inside bin e_on
        return int(edges[e_on]) + int(round((1.0 - f1) * b))
    f0 = min(max((c[e_on - 1] - floor) / h, 0.0), 1.0) if e_on > 0 else 0.0
    return int(edges[e_on]) - int(round(f0 * b))   # or already in the bin before


def _rise(c, m, floor_range, n, k, z, windows):
    """(onset edge, detection bin, floor, rise per bin, snr) with the floor taken from
    c[floor_range], or None when no sustained rise exceeds floor + k sigmas.

    The rise leaves the floor after the last n-bin window, before the detection, whose sum
    is still within floor + z sigmas: a burst that the signal drops back to the floor after
    is not part of it. The change point is then searched from that window on."""
    fa, fb = floor_range
    fl = _floor(c[fa:fb], n, k)
    i_hi = _first_sustained(m, fl.threshold, n, windows)
    if i_hi is None:
        return None
    nb = c.size
    sums = m[i_hi:i_hi + windows * n:n]
    rise = float(sums.mean()) / n
    snr = (float(sums.mean()) - fl.window_median) / fl.window_sigma
    at_floor = np.flatnonzero(m[:i_hi + 1] <= fl.window_median + z * fl.window_sigma)
    i_f = int(at_floor[-1]) if at_floor.size else 0
    e_on = _walk_back(c, fl.per_bin, rise, i_f, min(nb, i_f + 2 * n))
    return e_on, i_hi, fl, rise, snr


def smooth(c: np.ndarray, sigma_bins: float) -> np.ndarray:
    """Gaussian smoothing (sigma in bins) of a curve; a curve too short for the kernel is
    returned as it is."""
    r = max(1, int(math.ceil(3 * sigma_bins)))
    if sigma_bins <= 0 or c.size < 2 * r + 1:
        return c
    x = np.arange(-r, r + 1)
    w = np.exp(-0.5 * (x / sigma_bins) ** 2)
    return np.convolve(c, w / w.sum(), mode="same")


def _pearson_lags(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Pearson correlation of `y` with every length-len(y) window of `x` (one per lag)."""
    w = y.size
    y = y - y.mean()
    X = np.lib.stride_tricks.sliding_window_view(x, w)
    Xc = X - X.mean(axis=1, keepdims=True)
    den = np.sqrt((Xc ** 2).sum(axis=1) * (y ** 2).sum())
    return np.divide(Xc @ y, den, out=np.zeros(X.shape[0]), where=den > 0)


def _parabolic(r: np.ndarray, i: int) -> float:
    if not 0 < i < r.size - 1:
        return 0.0
    a, b, c = r[i - 1], r[i], r[i + 1]
    den = a - 2 * b + c
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if den < 0 else 0.0


def correlate_onsets(t_ref: np.ndarray, on_ref: int, t_view: np.ndarray, on_view: int, *,
                     fine_ns: int = 100_000, pre_ns: int = 3_000_000, post_ns: int = 20_000_000,
                     search_ns: int = 1_500_000, smooth_bins: float = 1.0) -> tuple[float, float, bool]:
    """Lag (ns, float) to add to `on_view` so that the view's early-motion rate curve lines up
    with the reference's at `on_ref`; with the correlation peak height and whether the peak
    lies inside the search range (not on its edge). Peak by parabola through its neighbours.

    The search range is deliberately narrow (the onsets already align the curves to about a
    bin): rate curves of a steady motion have ripples that repeat, and a wide search lets
    the correlation lock onto the wrong one."""
    s = max(1, int(round(search_ns / fine_ns)))
    pre = max(1, int(round(pre_ns / fine_ns)))
    post = max(1, int(round(post_ns / fine_ns)))
    _, cr = event_rate(t_ref, fine_ns, on_ref - pre * fine_ns, on_ref + post * fine_ns)
    _, cv = event_rate(t_view, fine_ns, on_view - (pre + s) * fine_ns, on_view + (post + s) * fine_ns)
    r = _pearson_lags(smooth(cr.astype(np.float64), smooth_bins), smooth(cv.astype(np.float64), smooth_bins))
    i = int(np.argmax(r))
    return ((i - s) + _parabolic(r, i)) * fine_ns, float(r[i]), 0 < i < r.size - 1
