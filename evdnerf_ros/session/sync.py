"""`evdnerf sync SESSION`: align the per-view recordings of a session on one time origin.

Every view of a session is a separate recording of the same repeatable motion, in its own
clock. Sync finds, in each view's clock, the time of one common physical instant (the
start of the motion) and writes it to session.yaml as ``views[i].sync.offset_ns``, so that
``t_common = t_view - offset_ns`` (see :mod:`evdnerf_ros.session.layout`). Bags are only
read, never rewritten.

Sources of the origin, best first (``method="auto"`` takes, per view, the best one present):

``trigger``
    The first rising EXT_TRIGGER edge in the view's event stream (a trigger cable raised at
    the start of the motion, e.g. the servo board's trigger-out at servo start; `evdnerf
    simulate` records one in every view), timestamped by the sensor itself: exact to the
    sensor's microsecond tick.
``start``
    The header stamp of the firmware's START ``sensor_msgs/TimeReference`` on the servo
    trigger topic (stamped by the host in the view's clock when the START line arrived;
    subject to the host's serial latency).
``rate``
    The event-rate curve: motion onset (:mod:`.onset`) refined to a fraction of a bin by
    cross-correlating this view's early-motion rate curve with the reference view's.
``onset``
    The motion onset of the event-rate curve alone (resolution: one bin).

The onset detection and the correlation are in :mod:`evdnerf_ros.session.onset` (described
there); this module reads the views, chooses a method per view and writes the records.

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

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..options import check_value, flag_name, option, option_fields
from ..topics import EVENT_TRIGGERS
from ..atomic import check_output
from ..events.rate import event_rate, plot_event_rate, save_figure
from .layout import load_session, session_topics
from .onset import Onset, correlate_onsets, detect_onset, hot_pixels, smooth
from .recorder import write_session_yaml

METHODS = ("auto", "trigger", "start", "rate", "onset")
#: Estimate keys in session.yaml, best first; ``rate`` is stored as ``rate_refined``.
ESTIMATE_KEYS = ("trigger", "start", "rate_refined", "rate_onset")
_METHOD_KEY = {"trigger": "trigger", "start": "start", "rate": "rate_refined", "onset": "rate_onset"}
_CONFIDENCE = {"trigger": 1.0, "start": 0.9}


@dataclass(frozen=True)
class SyncOptions:
    """Every knob of `evdnerf sync` (defaults in one place)."""

    bin_ns: int = option(1_000_000, "event-rate bin", flag="--bin", duration=True, low=1, high=3_600 * 10**9)
    method: str = option("auto", "force one method (auto: the best each view has)", choices=METHODS)
    reference_view: str | None = option(None, "reference view for refinement", kind=str, flag="--reference",
                                        none_help="the first training view")
    refine: bool = option(True, "skip the cross-correlation refinement")
    plot_path: str | None = option(None, "aligned rate plot path", kind=str, flag="--plot",
                                   none_help="SESSION/sync.png")
    overwrite: bool = option(False, "replace an existing --plot file (SESSION/sync.png, the default, is the "
                                    "session's own and always replaced; a folder never is)")
    events_topic: str | None = option(None, "event topic", kind=str, none_help="from session.yaml")
    trigger_topic: str | None = option(None, "servo START/DONE topic", kind=str, none_help="from session.yaml")
    trigger_id: int | None = option(None, "EXT_TRIGGER channel", kind=int, low=0, high=255, none_help="any")
    # onset detection (config file only: --config FILE)
    k: float = option(8.0, "detection threshold: floor + k robust sigmas ...", low=0, high=1e6, cli=False)
    sustain_ns: int = option(4_000_000, "... in windows this long (at least 1 bin) ...", duration=True,
                             low=1, high=3_600 * 10**9, cli=False)
    sustain_windows: int = option(5, "... this many in a row", low=1, high=1_000_000, cli=False)
    floor_z: float = option(1.5, "the rise starts after the last window within floor + z sigmas",
                            low=0, high=1e6, cli=False)
    quiet_ns: int = option(50_000_000, "lowest-rate stretch for the first floor estimate", duration=True,
                           low=1, high=3_600 * 10**9, cli=False)
    # hot pixels
    hot_k: float = option(10.0, "count outlier: median + hot_k robust sigmas", low=0, high=1e6, cli=False)
    hot_coverage: float = option(0.75, "fires in at least this fraction of the slices", low=0, high=1, cli=False)
    hot_dispersion: float = option(2.0, "per-slice variance / mean at most this", low=0, high=1e6, cli=False)
    hot_slices: int = option(16, "time slices of the hot-pixel test", low=1, high=1_000_000, cli=False)
    hot_min_events: int = option(20, "fewest events of a hot pixel", low=1, high=2**62, cli=False)
    # refinement
    refine_bin_ns: int = option(100_000, "fine bins of the correlated curves", duration=True,
                                low=1, high=3_600 * 10**9, cli=False)
    refine_anchor_ns: int = option(1_000_000, "onsets re-detected on bins of this to anchor the windows",
                                   duration=True, low=1, high=3_600 * 10**9, cli=False)
    refine_pre_ns: int = option(3_000_000, "correlation window: before the onset ...", duration=True,
                                low=1, high=3_600 * 10**9, cli=False)
    refine_post_ns: int = option(20_000_000, "... and after it (the early motion)", duration=True,
                                 low=1, high=3_600 * 10**9, cli=False)
    refine_search_ns: int = option(1_500_000, "lags searched: +- this around the anchors", duration=True,
                                   low=1, high=3_600 * 10**9, cli=False)
    refine_smooth_bins: float = option(1.0, "Gaussian sigma of the fine curves, in fine bins", low=0, high=1e6,
                                       cli=False)
    min_correlation: float = option(0.3, "weaker peaks keep the anchor", low=0, high=1, cli=False)

    def check(self) -> None:
        for f, spec in option_fields(SyncOptions):
            if f.name != "plot_path":           # a Path is fine here
                name = flag_name(f, spec) if spec.cli else f.name
                check_value(getattr(self, f.name), f, spec, f"sync: {name}")


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
        separate = EVENT_TRIGGERS != ev_topic and EVENT_TRIGGERS in bag.topics
    ev, tr = stream.events, stream.triggers
    if separate:              # a libcaer camera's edges, kept on their own topic (libcaer_driver)
        tr = np.sort(np.concatenate([tr, read_events(view.bag, EVENT_TRIGGERS).triggers]), order="t",
                     kind="stable")
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


def _no_onset(root: Path, vd: ViewData, bin_ns: int, why: str, *, views: int = 2) -> InputError:
    path = plot_event_rate(_rate_plot_path(root, vd.name), {vd.name: (vd.edges, vd.counts)},
                           title=f"{vd.name}: event rate (no motion onset found)")
    fix = (f"a session of one view needs no sync: `evdnerf convert {root}` takes its first event as t = 0 "
           "(or --origin)" if views == 1 else "check that the camera saw the motion, or sync this view by "
           "trigger/START")
    return InputError(f"sync: no motion onset found in view {vd.name} ({why}): {vd.onset_reason}; "
                      f"its event-rate plot ({bin_ns} ns bins) is saved at {path}; nothing else was "
                      f"written. {fix[0].upper() + fix[1:]}")


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
            raise _no_onset(root, vd, options.bin_ns, why, views=len(views))

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
                works = [k for k in ("trigger", "start", "rate", "onset") if _usable(vd, k)
                         and (k != "rate" or options.refine)]
                raise InputError(f"sync: view {vd.name} has no {m} estimate (available: "
                                 f"{', '.join(have) or 'none'}); use "
                                 + (f"--method {works[0]}" if works else "another recording: no method has an "
                                    "estimate for this view"))
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
        c = smooth(c.astype(np.float64), 2.0)
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
