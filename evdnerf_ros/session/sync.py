"""`evdnerf sync SESSION`: align the per-view recordings of a session on one time origin.

Every view of a session is a separate recording of the same repeatable motion, in its own
clock. Sync finds, in each view's clock, the time of one common physical instant (the
start of the motion) and writes it to session.yaml as ``views[i].sync.offset_ns``, so that
``t_common = t_view - offset_ns`` (see :mod:`evdnerf_ros.session.layout`). Bags are only
read, never rewritten.

Sources of the origin, best first (``method="auto"`` takes, per view, the best one present):

``trigger``
    The first rising EXT_TRIGGER edge in the view's event stream (the servo board's
    trigger-out at servo start, timestamped by the sensor itself: exact to the sensor's
    microsecond tick).
``start``
    The header stamp of the firmware's START ``sensor_msgs/TimeReference`` on the servo
    trigger topic (stamped by the host in the view's clock when the START line arrived;
    subject to the host's serial latency).
``rate``
    The event-rate curve: motion onset (below) refined to a fraction of a bin by
    cross-correlating this view's early-motion rate curve with the reference view's.
``onset``
    The motion onset of the event-rate curve alone (resolution: one bin).

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

What accuracy to expect: the trigger edge is exact to the sensor's microsecond; START to the
host's latency. The event rate is only as good as the motion's onset is sharp. A sudden
start (the paper's "sudden peak") gives the onset to about a bin and the refinement to
about 100 µs; a smooth start (the fork's minimum-jerk servo profile, whose speed grows from
zero) makes the first events come milliseconds after the motion begins, later in views
that see less of it, so rate-based sync of such a motion is good to milliseconds only, and
the reported disagreement with the trigger shows it (bench/results/sync.json). Measured there
on a noisy 96x72 Jet-Down session (10 views, 3 noise seeds): onset median 90-140 µs at
0.2-1 ms bins, refined median 29 µs and p90 75 µs at any bin; on the fork, trigger and START
are exact while the rate is off by ~10 ms (median). Known limit: a burst of jitter less
than one detection window (``sustain_ns``) before the onset merges with the rise and pulls
the onset early by the gap (the bench's worst view, ~6.5 ms); at 10 ms bins a burst in the
bin before the onset does the same.

Per view, ``confidence`` in [0, 1]: 1.0 for a trigger edge; 0.9 for START (host latency);
for the rate methods ``snr_factor * peak`` (refined) or ``snr_factor * 0.5`` (onset), with
``snr_factor = min(1, onset_snr / (2 k))`` and ``peak`` the correlation peak height (the
reference view correlates with itself: peak 1).

Mixing methods across views: rate-based origins lag the servo start by the time the
first pixels take to respond. When some views are synced by a better source and others by
rate, the rate estimates are corrected by the median (rate - best) difference over the
views that have both (``sync.method_bias_ns``), so that all offsets refer to the same
instant. How far the methods disagree is reported per view: the spread, over the methods
present in both this view and the reference view, of ``estimate(view) - estimate(reference)``
(``views[i].sync.disagreement_us``; the maximum over views is ``sync.max_disagreement_us``).

Errors (InputError, nothing written): no motion onset in a view that needs one (the view's
rate plot is saved as ``<session>/sync_rate_<view>.png`` and the message says so), a forced
method that a view does not provide, an origin outside the view's recording, an unknown
reference view, a missing events topic (the bag reader's error names the topic and the
topics present).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..atomic import check_output
from ..events.rate import event_rate, plot_event_rate, save_figure
from .layout import load_session, session_topics, write_session_yaml

METHODS = ("auto", "trigger", "start", "rate", "onset")
#: Estimate keys in session.yaml, best first; ``rate`` is stored as ``rate_refined``.
ESTIMATE_KEYS = ("trigger", "start", "rate_refined", "rate_onset")
_METHOD_KEY = {"trigger": "trigger", "start": "start", "rate": "rate_refined", "onset": "rate_onset"}
_CONFIDENCE = {"trigger": 1.0, "start": 0.9}


@dataclass(frozen=True)
class SyncOptions:
    """Every knob of `evdnerf sync` (defaults in one place)."""

    bin_ns: int = 1_000_000               # rate-curve bin
    method: str = "auto"                  # auto | trigger | start | rate | onset
    reference_view: str | None = None     # None: the first training view
    refine: bool = True                   # sub-bin refinement by cross-correlation
    plot_path: str | Path | None = None   # None: <session>/sync.png
    overwrite: bool = False               # replace an existing plot_path file (<session>/sync.png always is)
    events_topic: str | None = None       # None: session.yaml camera.topics.events
    trigger_topic: str | None = None      # None: session.yaml servo.trigger
    trigger_id: int | None = None         # EXT_TRIGGER channel (None: any)
    # onset detection
    k: float = 8.0                        # detection threshold: floor + k robust sigmas ...
    sustain_ns: int = 4_000_000           # ... in windows this long (at least 1 bin) ...
    sustain_windows: int = 5              # ... this many in a row
    floor_z: float = 1.5                  # the rise starts after the last window within floor + z sigmas
    quiet_ns: int = 50_000_000            # lowest-rate stretch for the first floor estimate
    # hot pixels
    hot_k: float = 10.0                   # count outlier: median + hot_k robust sigmas
    hot_coverage: float = 0.75            # fires in at least this fraction of the slices
    hot_dispersion: float = 2.0           # per-slice variance / mean at most this
    hot_slices: int = 16
    hot_min_events: int = 20
    # refinement
    refine_bin_ns: int = 100_000          # fine bins of the correlated curves
    refine_anchor_ns: int = 1_000_000     # onsets re-detected on bins of this anchor the windows
    refine_pre_ns: int = 3_000_000        # correlation window: before the onset ...
    refine_post_ns: int = 20_000_000      # ... and after it (the early motion)
    refine_search_ns: int = 1_500_000     # lags searched: +- this around the anchors
    refine_smooth_bins: float = 1.0       # Gaussian sigma of the fine curves, in fine bins
    min_correlation: float = 0.3          # weaker peaks keep the anchor

    def check(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"sync: --method must be one of {', '.join(METHODS)}, got {self.method!r}")
        for name in ("bin_ns", "sustain_ns", "quiet_ns", "sustain_windows", "hot_slices", "hot_min_events",
                     "refine_bin_ns", "refine_anchor_ns", "refine_pre_ns", "refine_post_ns",
                     "refine_search_ns"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0:
                raise InputError(f"sync: {name.replace('_', '-')} must be a positive integer, got {v!r}")
        for name in ("k", "floor_z", "hot_k", "hot_dispersion", "refine_smooth_bins"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"sync: {name.replace('_', '-')} must be finite and >= 0, got {v}")
        for name in ("hot_coverage", "min_correlation"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v <= 1):
                raise InputError(f"sync: {name.replace('_', '-')} must lie in [0, 1], got {v}")


# =========================================================================== building blocks


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


def _smooth(c: np.ndarray, sigma_bins: float) -> np.ndarray:
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
    r = _pearson_lags(_smooth(cr.astype(np.float64), smooth_bins), _smooth(cv.astype(np.float64), smooth_bins))
    i = int(np.argmax(r))
    return ((i - s) + _parabolic(r, i)) * fine_ns, float(r[i]), 0 < i < r.size - 1


# =========================================================================== per view


@dataclass
class ViewData:
    name: str
    split: str
    span: tuple[int, int]                 # recording [start, end) in the view clock
    t: np.ndarray                         # event times without hot pixels (sorted)
    events_total: int
    excluded_hot_pixels: int
    hot_events: int
    edges: np.ndarray
    counts: np.ndarray
    onset: Onset | None
    onset_reason: str
    trigger_ns: int | None
    start_ns: int | None
    estimates: dict = field(default_factory=dict)
    quality: dict = field(default_factory=dict)


def _start_stamp(bag, topic: str) -> int | None:
    from ..io.messages import time_reference_ns

    if topic not in bag.topics:
        return None
    for _, msg in bag.read_messages(topic):
        stamp, _, source = time_reference_ns(msg)
        if "START" in source.replace(":", " ").split():
            return int(stamp)
    return None


def load_view(view, session, options: SyncOptions, ev_topic: str, tr_topic: str) -> ViewData:
    """Read one view's bag and compute its rate curve, onset, trigger and START estimates."""
    from ..io.rosbag2 import open_bag, read_events

    stream = read_events(view.bag, ev_topic)
    with open_bag(view.bag) as bag:
        start_stamp = _start_stamp(bag, tr_topic)
        b0, b1 = bag.start_ns, bag.end_ns
    ev, tr = stream.events, stream.triggers
    width = stream.width or session.width
    height = stream.height or session.height
    lo = [x for x in (b0, int(ev["t"][0]) if ev.size else None, int(tr["t"][0]) if tr.size else None)
          if x is not None]
    hi = [x for x in (b1, int(ev["t"][-1]) if ev.size else None, int(tr["t"][-1]) if tr.size else None)
          if x is not None]
    span = (min(lo), max(hi) + 1) if lo else (0, 1)
    hot = hot_pixels(ev, width, height, *span, k=options.hot_k, coverage=options.hot_coverage,
                     dispersion=options.hot_dispersion,
                     slices=options.hot_slices, min_events=options.hot_min_events)
    if hot.size:
        pix = ev["y"].astype(np.int64) * width + ev["x"]
        bad = np.zeros(width * height, bool)
        bad[hot] = True
        keep = ~bad[pix]
        t = ev["t"][keep]
    else:
        t = ev["t"].copy()
    edges, counts = event_rate(t, options.bin_ns, *span, name="--bin")
    n = max(1, -(-int(options.sustain_ns) // int(options.bin_ns)))
    quiet = max(1, -(-int(options.quiet_ns) // int(options.bin_ns)))
    onset, reason = detect_onset(counts, edges, k=options.k, floor_z=options.floor_z, sustain_bins=n,
                                 windows=options.sustain_windows, quiet_bins=quiet)
    rising = tr[tr["value"] == 1]
    if options.trigger_id is not None:
        rising = rising[rising["id"] == options.trigger_id]
    return ViewData(name=view.name, split=view.split, span=span, t=t, events_total=int(ev.size),
                    excluded_hot_pixels=int(hot.size), hot_events=int(ev.size - t.size),
                    edges=edges, counts=counts, onset=onset, onset_reason=reason,
                    trigger_ns=int(rising["t"][0]) if rising.size else None, start_ns=start_stamp)


def _anchor(vd: ViewData, options: SyncOptions) -> int:
    """The onset the correlation windows are centred on: re-detected on `refine_anchor_ns`
    bins (1 ms: coarse bins place it only to a bin, fine bins hold too few events each to
    place it well), unless the two disagree by more than two bins of the coarser (then the
    curves found different rises and the view's own onset is kept)."""
    b = int(options.refine_anchor_ns)
    if options.bin_ns == b:
        return vd.onset.t_ns
    edges, counts = event_rate(vd.t, b, *vd.span)
    on, _ = detect_onset(counts, edges, k=options.k, floor_z=options.floor_z,
                         sustain_bins=max(1, -(-int(options.sustain_ns) // b)),
                         windows=options.sustain_windows, quiet_bins=max(1, -(-int(options.quiet_ns) // b)))
    if on is None or abs(on.t_ns - vd.onset.t_ns) > 2 * max(b, int(options.bin_ns)):
        return vd.onset.t_ns
    return on.t_ns


# =========================================================================== session


@dataclass
class SyncResult:
    root: Path
    session_yaml: Path
    plot: Path
    summary: dict                 # the top-level `sync` record
    views: dict                   # name -> the view's `sync` record
    data: dict                    # the whole new session.yaml


def _rate_plot_path(root: Path, name: str) -> Path:
    return root / f"sync_rate_{name}.png"


def _no_onset(root: Path, vd: ViewData, bin_ns: int, why: str) -> InputError:
    path = plot_event_rate(_rate_plot_path(root, vd.name), {vd.name: (vd.edges, vd.counts)},
                           title=f"{vd.name}: event rate (no motion onset found)")
    return InputError(f"sync: no motion onset found in view {vd.name} ({why}): {vd.onset_reason}; "
                      f"its event-rate plot ({bin_ns} ns bins) is saved at {path}; nothing else was "
                      "written. Check that the camera saw the motion, or sync this view by trigger/START")


def _usable(vd: ViewData, method: str) -> bool:
    return vd.estimates.get(_METHOD_KEY[method]) is not None


def sync_session(root, options: SyncOptions = SyncOptions(), *, log=None) -> SyncResult:
    """Compute every view's origin, write session.yaml's sync records and the aligned-rate plot."""
    from .. import __version__

    options.check()
    say = log or (lambda *_: None)
    root = Path(root)
    # The plot path is checked before any work; the session's own sync.png is replaced on a re-run.
    plot = Path(options.plot_path) if options.plot_path is not None else root / "sync.png"
    check_output(plot, overwrite=options.overwrite or plot == root / "sync.png")
    session = load_session(root)
    ev_topic, tr_topic = session_topics(session, options.events_topic, options.trigger_topic)
    if options.reference_view is not None:
        ref_name = session.view(options.reference_view).name
    else:
        train = [v for v in session.views if v.split == "train"]
        ref_name = (train or session.views)[0].name

    views: list[ViewData] = []
    for view in session.views:
        vd = load_view(view, session, options, ev_topic, tr_topic)
        vd.estimates = {"trigger": vd.trigger_ns, "start": vd.start_ns,
                        "rate_onset": None if vd.onset is None else vd.onset.t_ns, "rate_refined": None}
        views.append(vd)
        say(f"  {vd.name}: {vd.events_total} events, {vd.excluded_hot_pixels} hot pixels excluded, "
            f"onset {'none' if vd.onset is None else vd.onset.t_ns}, trigger {vd.trigger_ns}, "
            f"START {vd.start_ns}")
    by_name = {vd.name: vd for vd in views}
    ref = by_name[ref_name]

    # Which views need the rate curve? (then a missing onset is an error)
    need_rate = []
    for vd in views:
        if options.method in ("rate", "onset"):
            need_rate.append(vd)
        elif options.method == "auto" and vd.trigger_ns is None and vd.start_ns is None:
            need_rate.append(vd)
    for vd in need_rate:
        if vd.onset is None:
            why = (f"method {options.method}" if options.method != "auto"
                   else "no trigger edge and no START message either")
            raise _no_onset(root, vd, options.bin_ns, why)

    # Sub-bin refinement against the reference view.
    if options.refine and ref.onset is not None:
        anchors = {vd.name: _anchor(vd, options) for vd in views if vd.onset is not None}
        a_ref = anchors[ref.name]
        for vd in views:
            a_v = anchors.get(vd.name)
            if a_v is None:
                continue
            if vd is ref:
                lag, peak, inside = 0.0, 1.0, True
            else:
                lag, peak, inside = correlate_onsets(
                    ref.t, a_ref, vd.t, a_v, fine_ns=options.refine_bin_ns,
                    pre_ns=options.refine_pre_ns, post_ns=options.refine_post_ns,
                    search_ns=options.refine_search_ns, smooth_bins=options.refine_smooth_bins)
            ok = inside and peak >= options.min_correlation
            vd.estimates["rate_refined"] = int(a_v + (int(round(lag)) if ok else 0))
            vd.quality.update(correlation_peak=round(peak, 4), correlation_lag_us=round(lag / 1e3, 3),
                              refined=bool(ok))
    for vd in views:
        if vd.onset is not None:
            vd.quality.update(onset_snr=round(float(vd.onset.snr), 2),
                              floor_events_per_s=round(vd.onset.floor.per_bin * 1e9 / options.bin_ns, 3))

    # Choose per view.
    chosen: dict[str, str] = {}
    for vd in views:
        if options.method == "auto":
            order = ("trigger", "start", "rate", "onset") if options.refine else ("trigger", "start", "onset")
            m = next(m for m in order if _usable(vd, m))   # a view with none was refused above
        else:
            m = options.method
            if m == "rate" and not options.refine:
                raise InputError("sync: --method rate needs the refinement; drop --no-refine or use "
                                 "--method onset")
            if not _usable(vd, m):
                have = [k for k in ESTIMATE_KEYS if vd.estimates.get(k) is not None]
                raise InputError(f"sync: view {vd.name} has no {m} estimate (available: "
                                 f"{', '.join(have) or 'none'}); use --method auto")
        chosen[vd.name] = m

    # Refer every offset to the same instant: correct methods by their median bias against the
    # best method used, over views that have both.
    used = [m for m in ("trigger", "start", "rate", "onset") if m in chosen.values()]
    best = used[0]
    bias = {best: 0}
    for m in used[1:]:
        diffs = [vd.estimates[_METHOD_KEY[m]] - vd.estimates[_METHOD_KEY[best]] for vd in views
                 if vd.estimates.get(_METHOD_KEY[m]) is not None
                 and vd.estimates.get(_METHOD_KEY[best]) is not None]
        bias[m] = int(np.median(diffs)) if diffs else 0

    records = {}
    max_dis = 0.0
    for vd in views:
        m = chosen[vd.name]
        offset = int(vd.estimates[_METHOD_KEY[m]] - bias[m])
        if not vd.span[0] <= offset < vd.span[1]:
            raise InputError(f"sync: view {vd.name}: the {m} origin {offset} ns lies outside the view's "
                             f"recording [{vd.span[0]}, {vd.span[1]}) ns; the {m} source belongs to another "
                             "run or is corrupt; choose another --method")
        rel = [vd.estimates[key] - ref.estimates[key] for key in ESTIMATE_KEYS
               if vd.estimates.get(key) is not None and ref.estimates.get(key) is not None]
        dis = (max(rel) - min(rel)) / 1e3 if rel else 0.0
        max_dis = max(max_dis, dis)
        if m in _CONFIDENCE:
            conf = _CONFIDENCE[m]
        else:
            snr_factor = min(1.0, max(0.0, vd.onset.snr) / (2 * options.k)) if options.k > 0 else 1.0
            refined = m == "rate" and vd.quality.get("refined")
            conf = snr_factor * (max(0.0, vd.quality["correlation_peak"]) if refined else 0.5)
        records[vd.name] = {
            "offset_ns": offset,
            "method": m,
            "confidence": round(float(conf), 4),
            "estimates": {k: (None if vd.estimates.get(k) is None else int(vd.estimates[k]))
                          for k in ("trigger", "start", "rate_onset", "rate_refined")},
            "disagreement_us": round(float(dis), 3),
            "excluded_hot_pixels": vd.excluded_hot_pixels,
            "excluded_hot_events": vd.hot_events,
            "quality": {k: (float(v) if isinstance(v, (float, np.floating)) else v)
                        for k, v in vd.quality.items()},
        }
    summary = {
        "reference_view": ref.name,
        "bin_ns": int(options.bin_ns),
        "method": options.method,
        "refine": bool(options.refine),
        "refine_bin_ns": int(options.refine_bin_ns),
        "methods_used": sorted(set(chosen.values()), key=("trigger", "start", "rate", "onset").index),
        "method_bias_ns": {m: int(b) for m, b in bias.items() if m != best},
        "max_disagreement_us": round(float(max_dis), 3),
        "events_topic": ev_topic,
        "software_version": __version__,
    }

    plot_aligned(plot, views, records, options, ref.name)
    data = dict(session.data)
    new_views = []
    for v in data["views"]:
        v = dict(v)
        v["sync"] = records[v["name"]]
        new_views.append(v)
    data["views"] = new_views
    data["sync"] = summary
    path = write_session_yaml(root, data, overwrite=True)
    for vd in views:
        r = records[vd.name]
        say(f"  {vd.name}: offset {r['offset_ns']} ns by {r['method']} (confidence {r['confidence']:.2f}, "
            f"methods disagree by {r['disagreement_us']:.1f} us)")
    return SyncResult(root, path, plot, summary, records, data)


def plot_aligned(path, views: list[ViewData], records: dict, options: SyncOptions, ref_name: str) -> Path:
    """Two panels: every view's rate curve on the common time axis, and a zoom on the origin
    (fine bins, each curve scaled to its own maximum). Replaces a file at `path` only after
    sync_session checked that it may."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6))
    pre, post = max(options.refine_pre_ns, 10_000_000), max(options.refine_post_ns, 40_000_000)
    fine = max(options.refine_bin_ns, 250_000)
    for vd in views:
        off = records[vd.name]["offset_ns"]
        lw = 1.6 if vd.name == ref_name else 0.9
        bin_s = options.bin_ns * 1e-9
        x = (vd.edges[:-1] - off + options.bin_ns // 2) * 1e-9     # display only: int64 differences
        ax1.step(x, vd.counts / bin_s, where="mid", linewidth=lw,
                 label=f"{vd.name} ({records[vd.name]['method']})")
        e, c = event_rate(vd.t, fine, off - pre, off + post)
        c = _smooth(c.astype(np.float64), 2.0)
        top = c.max() if c.size and c.max() > 0 else 1.0
        ax2.plot((e[:-1] - off + fine // 2) * 1e-6, c / top, linewidth=lw)
    for ax in (ax1, ax2):
        ax.axvline(0.0, color="k", linewidth=0.6, linestyle="--")
    ax1.set_xlabel("common time [s]")
    ax1.set_ylabel("events / s")
    ax1.set_title(f"event rate, aligned (reference {ref_name}, bin {options.bin_ns / 1e6:g} ms)")
    ax1.legend(fontsize=7, ncol=2)
    ax2.set_xlabel("common time [ms]")
    ax2.set_ylabel("rate / max")
    ax2.set_title(f"around the origin ({fine / 1e3:g} us bins, smoothed)")
    fig.tight_layout()
    return save_figure(fig, path)


def run_sync(session_dir, *, bin_ns: int = 1_000_000, method: str = "auto",
             reference_view: str | None = None, refine: bool = True, plot_path=None,
             overwrite: bool = False, log=None, **options) -> dict:
    """The `evdnerf sync SESSION` entry point: sync, write, and return a JSON-able summary."""
    opts = replace(SyncOptions(), bin_ns=int(bin_ns), method=method, reference_view=reference_view,
                   refine=bool(refine), plot_path=plot_path, overwrite=bool(overwrite), **options)
    res = sync_session(session_dir, opts, log=log)
    return {"session": str(res.root), "session_yaml": str(res.session_yaml), "plot": str(res.plot),
            "sync": res.summary, "views": res.views}


# =========================================================================== robustness testing
