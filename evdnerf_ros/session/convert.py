"""`evdnerf convert SESSION -o TRAIN.h5`: a capture session (one rosbag2 per view) -> one
training set (layout: :mod:`evdnerf_ros.io.trainingset`).

What it does, per view, in one streaming pass over the bag (bounded memory: packets are
decoded and written in batches of ~2 M events, never a whole view at once):

1. **Clock offsets.** ``t_common = t_view - offset_ns``, with ``offset_ns`` from the view's
   ``sync`` record in session.yaml (written by ``evdnerf sync``; t = 0 is the common motion
   onset). A session without sync records is refused with a message to run
   ``evdnerf sync SESSION`` first. ``offsets="ground-truth"`` (simulated sessions only) uses
   the injected offsets instead: ``offset_ns = ground_truth.clock_offset_ns +
   time.motion_start_ns``, so that ``t_common = scene time - motion start`` (t = 0 is the true
   motion onset). A mapping {view name: offset_ns} may also be given directly.
2. **Time window** [start, end) in the common clock. Given, or automatic: start = 0 (the
   common motion onset) and end = ``time.motion_end_ns - time.motion_start_ns`` when
   session.yaml knows the motion span ("session-time"), else where the event rate summed
   over all views falls back to its floor for good ("rate-floor": 10 ms bins over the time
   every view covers; floor = the median count of the bins before t = 0, or of the last ten
   bins when that is lower; end = the end of the last bin after t = 0 whose count exceeds
   floor + max(5 sqrt(floor) + 1, 5 % of (peak - floor)); when the rate never falls back, the
   end of the common coverage). Events outside the window are dropped.
3. **Downsampling** (``downsample=2``): events keep their time and polarity; x // 2, y // 2,
   so that dL images at the new size are exactly the sums of 2x2 blocks of the full-size
   ones (the paper trains at 128^2 from 256^2 renders this way). An odd width or height
   loses its last column / row (those events are counted in the provenance).
   Intrinsics, with pixel centres at integer coordinates (OpenCV / ROS, and our renderer):
   new pixel j covers old pixels 2j and 2j+1, whose centre is old coordinate 2j + 0.5, so
   ``u' = (u + 0.5) / 2 - 0.5``: fx' = fx / 2, fy' = fy / 2, cx' = (cx + 0.5) / 2 - 0.5,
   cy' = (cy + 0.5) / 2 - 0.5. Blurred frames are averaged over the same 2x2 blocks.
4. **Intrinsics** from the bag's CameraInfo (``intrinsics="camera_info"``, default),
   cross-checked against session.yaml's camera (size exact, K to 1e-6 relative); a
   mismatch is an error. ``intrinsics="session"`` uses session.yaml alone. The event
   stream's declared size must equal the camera's: every view has one resolution.
5. **Poses**: the static ``T_world_cam`` of session.yaml. ``poses="auto"`` (default) also
   reads the pose topic when the bag has it: a camera that moves (poses differ by more than
   1e-6) gets its trajectory stored (times shifted to the common clock); a static pose that
   disagrees with session.yaml is an error. ``poses="topic"`` requires the topic (its first
   pose becomes the static pose); ``poses="session"`` ignores it. NaN or non-rigid poses are
   errors.
6. **Frames**: the view's blurred frames (.npz) are copied with their times shifted by the
   offset (``frames=False`` skips them).
7. **Provenance**: source bags, offsets and their source, the sync records, the window and
   how it was found, topics, software version, sha256 of session.yaml, and for a session that
   knows its scene (simulated, or captured on the virtual rig) what evaluation needs to render
   it (``truth``; else ``truth_note``: why not, when the scene is known but a view's time in it
   is not).

Errors (all :class:`~evdnerf_ros.errors.EvdnerfError`, naming the view and its bag; the output
is written through :func:`~evdnerf_ros.atomic.atomic_output`, so nothing is left behind):
missing sync records, missing topics (the message lists the topics present), views of
different resolutions, intrinsics that disagree with session.yaml, NaN / non-rigid poses,
duplicate view names (session.yaml is refused on load), an offset that puts the window
outside the view's recording (with an automatic window: t = 0 more than 100 ms before the
bag's first message or after its last), unsorted or out-of-bounds events, and a damaged or
**truncated bag**, which raises :class:`~evdnerf_ros.errors.FormatError`
``convert: view NAME (BAG): ... truncated ...`` (a missing MCAP footer or fewer messages
than the bag's index lists).
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .. import __version__
from ..atomic import PARTIAL_SUFFIX, atomic_output
from ..errors import EvdnerfError, FormatError, InputError, OutputExistsError
from ..io.guard import OutputWriteError, check_free_space
from ..limits import check_memory
from ..geometry.poses import check_rigid
from ..io.evdnerf_format import EVENT_TIMES
from ..io.trainingset import COMPRESSIONS, TrainingSetWriter
from ..options import check_value, flag_name, option, option_fields
from ..topics import CAMERA_INFO, CAMERA_POSE, EVENTS
from .layout import Session, ViewRecord, load_session, session_yaml_path

#: The topics convert reads, by role (session.yaml's camera.topics may name others).
DEFAULT_TOPICS = {"events": EVENTS, "camera_info": CAMERA_INFO, "pose": CAMERA_POSE}
OFFSET_SOURCES = ("sync", "ground-truth")
POSE_SOURCES = ("auto", "session", "topic")
INTRINSICS_SOURCES = ("camera_info", "session")
FORMATS = ("h5", "evdnerf")
DOWNSAMPLE = (1, 2)
#: Relative tolerance of the CameraInfo / session.yaml intrinsics cross-check.
K_RTOL = 1e-6
#: Two poses farther apart than this (max abs difference of the 4x4 entries) differ.
POSE_TOL = 1e-6
RATE_BIN_NS = 10_000_000
#: With an automatic window, t = 0 may lie this much before the first message of a view's bag
#: (a recording that starts a moment after the motion onset); farther is an error.
SPAN_SLACK_NS = 100_000_000
BATCH_EVENTS = 1 << 21


@dataclass(frozen=True)
class ConvertOptions:
    """Every knob of `evdnerf convert` (the CLI flags map one to one)."""

    fmt: str = option("h5", "output format: our TRAIN.h5, or the EvDNeRF paper's folder", flag="--format",
                      choices=FORMATS)
    window: tuple[int, int] | None = option(None, "[start, end) in the common clock (ns or '10ms')", kind=int,
                                            nargs=2, duration=True, low=-2**62, high=2**62, cli=False,
                                            none_help="the motion window")
    downsample: int = option(1, "2: sum events over 2x2 pixel blocks, as the paper does", choices=DOWNSAMPLE)
    crop: tuple[int, int, int, int] | None = option(None, "keep only the sensor window X Y W H (before "
                                                    "downsampling; K shifted): a scene that fills part of the sensor",
                                                    kind=int, nargs=4, low=0, high=65535,
                                                    metavar=("X", "Y", "W", "H"), none_help="the whole sensor")
    # "sync" | "ground-truth" | (library only) {view: offset_ns}
    offsets: str | Mapping = option("sync", "clock offsets from `evdnerf sync` or, for simulated sessions, the "
                                            "injected ground truth", choices=OFFSET_SOURCES)
    origin: int | None = option(None, "a single-view session without a sync record: its time origin (t = 0) "
                                      "in the view's own clock (e.g. '1675956551250000000ns')",
                                kind=int, duration=True,
                                low=-2**62, high=2**62, none_help="its first event")
    poses: str = option("auto", "camera poses from session.yaml (static) or the pose topic (moving camera)",
                        choices=POSE_SOURCES)
    intrinsics: str = option("camera_info", "intrinsics from each bag's CameraInfo (checked against "
                                            "session.yaml) or from session.yaml", choices=INTRINSICS_SOURCES)
    frames: bool = option(True, "leave out the blurred frames")
    compression: str = option("scaleoffset", "lossless HDF5 filter: scaleoffset (fast) or gzip (smaller)",
                              choices=COMPRESSIONS)
    rate_bin_ns: int = option(RATE_BIN_NS, "automatic motion end: rate-curve bin", duration=True,
                              low=1, high=3_600 * 10**9, cli=False)
    # [[xmin, ymin, zmin], [xmax, ymax, zmax]] (m); library only
    scene_bounds: tuple | None = None
    topics: Mapping | None = None              # overrides of DEFAULT_TOPICS / session.yaml's topics
    batch_events: int = option(BATCH_EVENTS, "events decoded per batch", low=1, high=2**40, cli=False)
    # --format evdnerf
    n_windows: int = option(32, "--format evdnerf: event frames per view", low=1, high=100_000)
    event_time: str = option("normalized", "--format evdnerf: time column of their event arrays",
                             choices=EVENT_TIMES)
    raw_events: bool = option(True, "--format evdnerf: leave out their per-view (N, 4) event arrays")

    def check(self) -> None:
        for f, spec in option_fields(ConvertOptions):
            value = getattr(self, f.name)
            if f.name == "offsets" and isinstance(value, Mapping):
                continue
            check_value(value, f, spec, f"convert: {flag_name(f, spec) if spec.cli else f.name}")
        if self.crop is not None and (int(self.crop[2]) < 1 or int(self.crop[3]) < 1):
            raise InputError(f"convert: --crop {' '.join(map(str, self.crop))}: width and height must be >= 1")
        if self.window is not None and int(self.window[1]) <= int(self.window[0]):
            raise InputError(f"convert: window end {self.window[1]} ns must be after its start {self.window[0]} ns")


# =========================================================================== pieces


def resolve_offsets(session: Session, offsets="sync", *, origin: int | None = None,
                    topic: str = EVENTS) -> tuple[dict[str, int], str]:
    """{view name: offset_ns} (t_common = t_view - offset_ns) and where they came from. A session
    of one view needs no sync: its origin is ``origin`` (in its own clock) or its first event on
    ``topic``."""
    root = session.root
    out: dict[str, int] = {}
    one = len(session.views) == 1 and not isinstance(session.views[0].sync, Mapping)
    if origin is not None and not (offsets == "sync" and one):
        raise InputError("convert: --origin sets the time origin of a single-view session without a sync record; "
                         f"{root} has {len(session.views)} view(s)"
                         + ("" if len(session.views) != 1 else " and a sync record (or other --offsets)"))
    if offsets == "sync" and one:
        v = session.views[0]
        if origin is not None:
            return {v.name: int(origin)}, "--origin"
        return {v.name: _first_event_ns(v.bag, topic)}, "first event"
    if isinstance(offsets, Mapping):
        for v in session.views:
            if v.name not in offsets:
                raise InputError(f"convert: no offset given for view {v.name}")
            out[v.name] = _as_int_ns(offsets[v.name], f"offset of view {v.name}")
        return out, "given"
    if offsets == "sync":
        missing = [v.name for v in session.views
                   if not isinstance(v.sync, Mapping) or v.sync.get("offset_ns") is None]
        if missing:
            raise InputError(
                f"{session_yaml_path(root)}: view(s) {', '.join(missing)} have no sync record "
                f"(views[].sync.offset_ns); run `evdnerf sync {root}` first to align the views' clocks"
                " (for a simulated session, `--offsets ground-truth` uses the injected offsets instead)")
        for v in session.views:
            out[v.name] = _as_int_ns(v.sync["offset_ns"], f"view {v.name}: sync.offset_ns")
        return out, "sync"
    # ground truth (simulated sessions)
    motion_start = session.time.get("motion_start_ns")
    if motion_start is None:
        motion_start = session.time.get("scene_start_ns")
    for v in session.views:
        gt = v.ground_truth if isinstance(v.ground_truth, Mapping) else {}
        if gt.get("clock_offset_ns") is None or motion_start is None:
            raise InputError(f"{session_yaml_path(root)}: view {v.name} has no ground_truth.clock_offset_ns "
                             "(or time.motion_start_ns is missing): `--offsets ground-truth` works only for "
                             f"sessions written by `evdnerf simulate`; run `evdnerf sync {root}` instead")
        out[v.name] = _as_int_ns(gt["clock_offset_ns"], f"view {v.name}: ground_truth.clock_offset_ns") \
            + _as_int_ns(motion_start, "time.motion_start_ns")
    return out, "ground-truth"


def _first_event_ns(bag, topic: str) -> int:
    """The time of a bag's first event on ``topic`` (reading message by message until one has events)."""
    from ..io.bag_reader import iter_event_packets

    for packet in iter_event_packets(bag, topic):
        if packet.events.size:
            return int(packet.events["t"][0])
    raise InputError(f"convert: {bag}: topic {topic} holds no events; nothing to convert")


def _as_int_ns(value, what) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"convert: {what} must be an integer number of ns, got {value!r}")
    return int(value)


def downsample_K(K: np.ndarray, factor: int) -> np.ndarray:
    """Intrinsics after binning `factor` x `factor` pixel blocks (pixel centres at integer
    coordinates): f' = f / s, c' = (c + 0.5) / s - 0.5."""
    K = np.array(K, np.float64)
    if factor == 1:
        return K
    s = float(factor)
    K[0, 0] /= s
    K[1, 1] /= s
    K[0, 1] /= s
    K[0, 2] = (K[0, 2] + 0.5) / s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / s - 0.5
    return K


def downsample_frames(frames: np.ndarray, factor: int) -> np.ndarray:
    """(N, H, W) -> (N, H // s, W // s): means over s x s blocks (odd edges dropped)."""
    if factor == 1:
        return frames
    n, h, w = frames.shape
    h2, w2 = h // factor, w // factor
    f = frames[:, :h2 * factor, :w2 * factor].astype(np.float64)
    return f.reshape(n, h2, factor, w2, factor).mean(axis=(2, 4)).astype(np.float32)


def _topics(session: Session, options: ConvertOptions) -> dict[str, str]:
    topics = dict(DEFAULT_TOPICS)
    cam = session.data.get("camera") or {}
    if isinstance(cam.get("topics"), Mapping):
        topics.update({k: str(v) for k, v in cam["topics"].items() if k in topics and v})
    if options.topics:
        for k, v in options.topics.items():
            if k not in topics:
                raise InputError(f"convert: unknown topic role {k!r}; roles: {list(topics)}")
            topics[k] = str(v)
    return topics


class _RateHistogram:
    """Event counts in fixed int64 bins (floor(t / bin)), growing to cover any sorted batch."""

    def __init__(self, bin_ns: int):
        self.bin_ns = int(bin_ns)
        self.first: int | None = None
        self.counts = np.zeros(0, np.int64)

    def add(self, t: np.ndarray) -> None:
        if t.size == 0:
            return
        b0, b1 = int(t[0]) // self.bin_ns, int(t[-1]) // self.bin_ns
        lo = b0 if self.first is None else min(b0, self.first)
        check_memory(16 * (max(b1 - lo + 1, self.counts.size) + 1), f"convert: an event-rate curve of "
                     f"{b1 - lo + 1} bins of {self.bin_ns} ns (events from {lo * self.bin_ns} to {t[-1]} ns)",
                     "the events span an implausible time: a damaged bag or wrong sync offsets; give the "
                     "window explicitly (--start/--end)")
        if self.first is None:
            self.first = b0
        if b0 < self.first:
            self.counts = np.concatenate([np.zeros(self.first - b0, np.int64), self.counts])
            self.first = b0
        need = b1 - self.first + 1
        if need > self.counts.size:
            grown = np.zeros(max(need, self.counts.size * 3 // 2), np.int64)
            grown[:self.counts.size] = self.counts
            self.counts = grown
        c = np.bincount(t // self.bin_ns - b0, minlength=b1 - b0 + 1)
        self.counts[b0 - self.first:b1 - self.first + 1] += c


def detect_motion_end(counts: np.ndarray, first_bin: int, bin_ns: int, start_ns: int,
                      coverage: tuple[int, int]) -> tuple[int, dict]:
    """End of the motion (see the module doc, "rate-floor"): (end_ns, diagnostics)."""
    # counts over every bin that overlaps the coverage (bins without events count 0)
    b0, b1 = int(coverage[0]) // bin_ns, int(coverage[1]) // bin_ns
    check_memory(40 * max(0, b1 - b0 + 1), f"convert: an event-rate curve of {b1 - b0 + 1} bins over the views' "
                 f"common recording [{coverage[0]}, {coverage[1]}] ns",
                 "the recordings span an implausible time: a damaged bag or wrong sync offsets; give the window "
                 "explicitly (--start/--end)")
    full = np.zeros(max(0, b1 - b0 + 1), np.int64)
    lo, hi = max(b0, first_bin), min(b1, first_bin + counts.size - 1)
    if hi >= lo:
        full[lo - b0:hi - b0 + 1] = counts[lo - first_bin:hi - first_bin + 1]
    counts, first_bin = full, b0
    n = counts.size
    starts = (first_bin + np.arange(n, dtype=np.int64)) * bin_ns
    ends = starts + bin_ns
    valid = (starts >= coverage[0]) & (ends <= coverage[1] + 1)
    pre = valid & (ends <= start_ns)
    post = valid & (starts >= start_ns)
    if not post.any():
        raise InputError(f"convert: the views' common recording ends before t={start_ns} ns; no time after "
                         "the motion onset to convert (check the sync offsets, or give --window)")
    floors = []
    if pre.sum() >= 3:
        floors.append(float(np.median(counts[pre])))
    tail = counts[post][-10:]
    floors.append(float(np.median(tail)))
    floor = min(floors)
    peak = float(counts[post].max())
    threshold = floor + max(5.0 * math.sqrt(floor) + 1.0, 0.05 * (peak - floor))
    above = np.flatnonzero(post & (counts > threshold))
    if above.size == 0:
        raise InputError(f"convert: no motion found after t={start_ns} ns: the summed event rate never rises "
                         f"above its floor ({floor:.0f} events per {bin_ns} ns bin); check the sync offsets, "
                         "or give the window explicitly (--window START END)")
    end = int(ends[above[-1]])
    fell_back = bool(above[-1] < np.flatnonzero(post)[-1])
    end = min(end, coverage[1] + 1)
    return end, {"floor_per_bin": floor, "peak_per_bin": peak, "threshold_per_bin": threshold,
                 "bin_ns": int(bin_ns), "rate_fell_back": fell_back}


@dataclass
class _ViewPlan:
    record: ViewRecord
    offset_ns: int
    K: np.ndarray
    T_world_cam: np.ndarray
    poses_t: np.ndarray | None = None
    poses_T: np.ndarray | None = None
    moving: bool = False
    bag_span: tuple[int, int] | None = None
    stats: dict = field(default_factory=dict)


def _view_context(name: str, bag) -> str:
    return f"convert: view {name} ({bag})"


def _reraise(exc: EvdnerfError, name: str, bag):
    if isinstance(exc, (OutputExistsError, OutputWriteError)):
        return exc                        # about the output, not the view
    msg = f"{_view_context(name, bag)}: {exc}"
    if isinstance(exc, FormatError) and exc.source is not None and not str(exc.source).startswith(str(bag)):
        err = FormatError(msg)            # another file of the view (its frames), not its bag
    elif isinstance(exc, FormatError):
        hint = "" if "truncated" in str(exc) else "; the bag is damaged or truncated"
        err = FormatError(msg + hint + " (re-record the view, salvage it with `mcap recover`, or remove "
                          "it from session.yaml)")
    elif isinstance(exc, OutputExistsError):
        return exc
    else:
        err = type(exc)(msg) if type(exc) in (InputError, EvdnerfError) else InputError(msg)
    return err


def _plan_view(session: Session, v: ViewRecord, offset: int, topics: dict, options: ConvertOptions,
               log) -> _ViewPlan:
    """Open the view's bag once: topics, CameraInfo cross-check, poses, recording span."""
    from ..io.messages import intrinsics_from_camera_info, pose_from_pose_stamped
    from ..io.rosbag2 import open_bag

    if not v.bag.exists():
        raise InputError(f"bag {v.bag} does not exist (session.yaml views[].bag)")
    plan = _ViewPlan(record=v, offset_ns=offset, K=session.K.copy(), T_world_cam=v.T_world_cam.copy())
    with open_bag(v.bag) as bag:
        present = bag.topics
        listing = ", ".join(f"{n} [{t.msgtype}]" for n, t in present.items()) or "none"
        if topics["events"] not in present:
            raise InputError(f"no event topic {topics['events']!r}; topics in this bag: {listing}")
        if present[topics["events"]].message_count == 0:
            raise InputError(f"event topic {topics['events']} has no messages")
        plan.bag_span = (bag.start_ns, bag.end_ns)
        if options.intrinsics == "camera_info":
            if topics["camera_info"] not in present:
                raise InputError(f"no CameraInfo topic {topics['camera_info']!r}; topics in this bag: {listing} "
                                 "(use --intrinsics session to take the intrinsics from session.yaml)")
            msg = next((m for _, m in bag.read_messages(topics["camera_info"])), None)
            if msg is None:
                raise InputError(f"CameraInfo topic {topics['camera_info']} has no messages")
            info = intrinsics_from_camera_info(msg)
            if (info["width"], info["height"]) != (session.width, session.height):
                raise InputError(f"CameraInfo says {info['width']}x{info['height']} but session.yaml's camera is "
                                 f"{session.width}x{session.height}; every view must have the session's "
                                 "resolution")
            if not np.allclose(info["K"], session.K, rtol=K_RTOL, atol=1e-9):
                raise InputError(f"CameraInfo K {info['K'].tolist()} disagrees with session.yaml camera.K "
                                 f"{session.K.tolist()}; fix session.yaml (or the calibration) so they agree")
            plan.K = info["K"].copy()
        if options.poses != "session":
            if topics["pose"] not in present:
                if options.poses == "topic":
                    raise InputError(f"no pose topic {topics['pose']!r}; topics in this bag: {listing}")
            else:
                stamps, mats = [], []
                for i, (_, msg) in enumerate(bag.read_messages(topics["pose"])):
                    try:
                        T, stamp, _frame = pose_from_pose_stamped(msg)
                    except EvdnerfError as exc:
                        raise InputError(f"pose topic {topics['pose']}, message {i}: {exc}") from None
                    check_rigid(T, f"pose topic {topics['pose']}, message {i}")
                    stamps.append(stamp)
                    mats.append(T)
                if stamps:
                    t = np.asarray(stamps, np.int64) - offset
                    Ts = np.stack(mats)
                    order = np.argsort(t, kind="stable")
                    t, Ts = t[order], Ts[order]
                    moving = bool(np.abs(Ts - Ts[0]).max() > POSE_TOL)
                    if moving:
                        plan.poses_t, plan.poses_T, plan.moving = t, Ts, True
                        if options.poses == "topic":
                            plan.T_world_cam = Ts[0].copy()
                    elif options.poses == "topic":
                        plan.T_world_cam = Ts[0].copy()
                    elif np.abs(Ts[0] - v.T_world_cam).max() > POSE_TOL:
                        raise InputError(f"pose topic {topics['pose']} says T_world_cam = {Ts[0].tolist()} but "
                                         f"session.yaml says {v.T_world_cam.tolist()}; fix session.yaml, or "
                                         "choose one with --poses topic / --poses session")
                elif options.poses == "topic":
                    raise InputError(f"pose topic {topics['pose']} has no messages")
    return plan


def _check_span(plan: _ViewPlan, start: int, end: int | None) -> None:
    """The window (in the view's clock) must overlap the recording."""
    a, b = plan.bag_span
    lo = start + plan.offset_ns
    if end is None:
        inside = a - SPAN_SLACK_NS <= lo <= b
    else:
        inside = lo <= b and end + plan.offset_ns > a
    if not inside:
        where = (f"time {start} ns" if end is None else f"window [{start}, {end}) ns")
        raise InputError(f"the common {where} maps to view-clock {lo} ns with offset_ns={plan.offset_ns}, "
                         f"outside the recording [{a}, {b}] ns of this bag: the offset lies beyond the "
                         "recording (re-run `evdnerf sync`, or fix views[].sync.offset_ns)")


def _check_crop(crop, width: int, height: int):
    """The crop window (x, y, w, h) inside the sensor, or None."""
    if crop is None:
        return None
    x, y, w, h = map(int, crop)
    if x + w > width or y + h > height:
        raise InputError(f"convert: --crop {x} {y} {w} {h} reaches beyond the {width}x{height} sensor; choose a "
                         "window inside it")
    return x, y, w, h


def crop_K(K, crop) -> np.ndarray:
    """Intrinsics of a sensor window: the principal point moves by the window's origin."""
    K = np.array(K, np.float64)
    if crop is not None:
        K[0, 2] -= crop[0]
        K[1, 2] -= crop[1]
    return K


def _load_frames(v: ViewRecord, offset: int, factor: int, width: int, height: int, crop=None) -> dict | None:
    from ..io.npz import load_npz

    if v.frames is None:
        return None
    if not Path(v.frames).is_file():
        raise InputError(f"frames file {v.frames} (session.yaml views[].frames) does not exist")
    data = load_npz(v.frames, ("frames", "t_start", "t_end"), optional=("t",),
                    what="a frames file (frames (N, H, W) float, t_start, t_end int64 ns)")
    frames = data["frames"]
    if frames.ndim != 3 or frames.shape[1:] != (height, width) or frames.dtype.kind not in "fiu":
        raise InputError(f"frames file {v.frames}: frames have shape {frames.shape} and dtype {frames.dtype}, "
                         f"expected (N, {height}, {width}) numbers")
    frames = frames.astype(np.float32, copy=False)
    if not np.all(np.isfinite(frames)):
        raise InputError(f"frames file {v.frames}: frames contain NaN or inf")
    if crop is not None:
        x, y, cw, ch = crop
        frames = frames[:, y:y + ch, x:x + cw]
    out = {"frames": downsample_frames(frames, factor)}
    for k in ("t_start", "t_end", "t"):
        if k in data:
            a = data[k]
            if a.dtype.kind not in "iu" or a.shape != (frames.shape[0],):
                raise InputError(f"frames file {v.frames}: {k} must be {frames.shape[0]} int64 ns times, got "
                                 f"shape {a.shape} and dtype {a.dtype}")
            if a.size and (int(a.max()) > 2**62 or int(a.min()) < -2**62):
                raise InputError(f"frames file {v.frames}: {k} holds times beyond +-2**62 ns")
            out[k] = a.astype(np.int64) - offset
    return out


def _input_bytes(plans) -> int:
    """Bytes of the views' bags and frames files (for the free-space check)."""
    total = 0
    for plan in plans:
        v = plan.record
        for p in (v.bag, v.frames):
            if p is None:
                continue
            p = Path(p)
            try:
                total += sum(f.stat().st_size for f in p.iterdir() if f.is_file()) if p.is_dir() else p.stat().st_size
            except OSError:
                pass
    return total


# =========================================================================== convert


def convert_session(session_dir, out, options: ConvertOptions = ConvertOptions(), *, overwrite: bool = False,
                    log=print) -> dict:
    """Convert a session folder into a training set .h5 at `out` (atomically); returns a summary."""
    options.check()
    wall0 = time.perf_counter()
    if (Path(out).exists() or Path(out).is_symlink()) and not overwrite:
        raise OutputExistsError(out)              # before the (long) work, not after it
    session = load_session(session_dir)
    root = session.root
    frame_ns = _twin_frame_ns(session)             # checked before any work
    topics = _topics(session, options)
    offsets, offsets_source = resolve_offsets(session, options.offsets, origin=options.origin, topic=topics["events"])
    if offsets_source in ("--origin", "first event"):
        (name, origin), = offsets.items()
        log(f"  {name}: one view, no sync needed: time origin {origin} ns of its clock ({offsets_source})")
    s = options.downsample
    crop = _check_crop(options.crop, session.width, session.height)
    W0, H0 = (session.width, session.height) if crop is None else crop[2:]
    W, H = W0 // s, H0 // s
    if W < 1 or H < 1:
        raise InputError(f"convert: a {W0}x{H0} camera cannot be downsampled by {s}")

    # ----- the window
    motion = (session.time.get("motion_start_ns"), session.time.get("motion_end_ns"))
    if options.window is not None:
        start, end = int(options.window[0]), int(options.window[1])
        window_source = "given"
    elif motion[0] is not None and motion[1] is not None and int(motion[1]) > int(motion[0]):
        start, end = 0, int(motion[1]) - int(motion[0])
        window_source = "session-time"
    else:
        start, end = 0, None
        window_source = "rate-floor"

    plans: list[_ViewPlan] = []
    for v in session.views:
        try:
            plan = _plan_view(session, v, offsets[v.name], topics, options, log)
            _check_span(plan, start, end)
        except EvdnerfError as exc:
            raise _reraise(exc, v.name, v.bag) from None
        plans.append(plan)
    Ks = [p.K for p in plans]
    scene_bounds = options.scene_bounds if options.scene_bounds is not None else session.data.get("scene_bounds")

    rate = _RateHistogram(options.rate_bin_ns) if end is None else None
    coverage = [None, None]
    total_in, total_out = 0, 0
    # a training set takes at least about a quarter of its bags' bytes (more with frames): refuse
    # now a disk that clearly cannot hold it, not after minutes of decoding
    check_free_space(out, _input_bytes(plans) / 4, f"a training set from {len(plans)} views")
    with atomic_output(out, overwrite=overwrite) as tmp:
        with TrainingSetWriter(tmp, width=W, height=H, c_pos=session.c_pos, c_neg=session.c_neg, t_start=start,
                               t_end=end, eps=session.eps, downsample=s, compression=options.compression,
                               display=out) as w:
            for plan, K in zip(plans, Ks):
                v = plan.record
                t_view = time.perf_counter()
                try:
                    vw = w.add_view(v.name, split=v.split, K=downsample_K(crop_K(K, crop), s),
                                    T_world_cam=plan.T_world_cam,
                                    poses_t=plan.poses_t, poses_T=plan.poses_T,
                                    attrs={"offset_ns": np.int64(plan.offset_ns), "source_bag": str(v.bag),
                                           "azimuth_deg": np.nan if v.azimuth_deg is None else v.azimuth_deg,
                                           "D": np.asarray(session.D, np.float64)})
                    stats = _stream_view(v, plan.offset_ns, topics["events"], start, end, s, W0, H0, vw, rate,
                                         options.batch_events, crop, (session.width, session.height))
                    if options.frames:
                        fr = _load_frames(v, plan.offset_ns, s, session.width, session.height, crop)
                        if fr is not None:
                            vw.add_frames(fr["frames"], fr["t_start"], fr["t_end"], fr.get("t"))
                except EvdnerfError as exc:
                    raise _reraise(exc, v.name, v.bag) from None
                plan.stats = stats
                total_in += stats["events_decoded"]
                if stats["first_t"] is not None:     # the time every view recorded (bag span, common clock)
                    a, b = plan.bag_span[0] - plan.offset_ns, plan.bag_span[1] - plan.offset_ns
                    coverage[0] = a if coverage[0] is None else max(coverage[0], a)
                    coverage[1] = b if coverage[1] is None else min(coverage[1], b)
                secs = time.perf_counter() - t_view
                kept = "in the window" if end is not None else f"after t={start} ns (cut at the motion end later)"
                log(f"  {v.name}: {stats['events_decoded']} events decoded, {stats['events_in_window']} {kept}, "
                    f"{secs:.2f} s")

            end_info = {}
            if end is None:
                if coverage[0] is None or rate.first is None:
                    raise InputError(f"convert: {root}: no events in any view; nothing to convert")
                end, end_info = detect_motion_end(rate.counts, rate.first, rate.bin_ns, start,
                                                  (coverage[0], coverage[1]))
                log(f"  motion end from the summed event rate: t = {end} ns")
            prov_views = {}
            for plan in plans:
                v = plan.record
                prov_views[v.name] = {
                    "bag": str(Path(v.bag).resolve()), "split": v.split, "offset_ns": plan.offset_ns,
                    "sync": v.sync, "ground_truth_clock_offset_ns": (v.ground_truth or {}).get("clock_offset_ns"),
                    "ground_truth_sensor_zero_scene_ns": (v.ground_truth or {}).get("sensor_zero_scene_ns"),
                    "ground_truth_stale_renders": (v.ground_truth or {}).get("stale_renders"),
                    "moving_camera": plan.moving,
                    **{k: plan.stats[k] for k in ("events_decoded", "dropped_odd_edge", "outside_crop")},
                }
            provenance = {
                "software": "evdnerf_ros", "software_version": __version__,
                "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "command": "convert", "session_dir": str(Path(root).resolve()),
                "session_yaml_sha256": hashlib.sha256(session_yaml_path(root).read_bytes()).hexdigest(),
                "session_source": session.data.get("source"),
                "offsets_source": offsets_source, "sync_summary": session.data.get("sync"),
                "window": {"start_ns": start, "end_ns": end, "source": window_source, **end_info},
                "downsample": s, "source_size": [session.width, session.height],
                "crop": None if crop is None else list(crop),
                "K_scaling": "fx' = fx/s, fy' = fy/s, cx' = (cx+0.5)/s - 0.5, cy' = (cy+0.5)/s - 0.5",
                "intrinsics_source": options.intrinsics, "poses_source": options.poses, "topics": topics,
                "views": prov_views,
            }
            truth, no_truth = _truth_record(session.data.get("source"), prov_views, session.data.get("options"),
                                            frame_ns=frame_ns,
                                            servo_tracks={p.record.name: (p.record.ground_truth or {}).get("servo_track")
                                                          for p in plans})
            if truth is not None:
                provenance["truth"] = truth
                joint = _joint_record(session.servo, truth)
                if joint is not None:
                    provenance["joint"] = joint
            elif no_truth:              # a session that knows its scene, but not every view's time in it
                provenance["truth_note"] = no_truth
                log(f"  {no_truth}")
            w.finish(t_end=end, provenance=provenance, scene_bounds=scene_bounds,
                     attrs={"offsets_source": offsets_source, "window_source": window_source})
            for plan in plans:
                total_out += w.views[plan.record.name].n
            counts = {p.record.name: w.views[p.record.name].n for p in plans}
    seconds = time.perf_counter() - wall0
    log(f"convert: {len(plans)} views, {total_out} events in [{start}, {end}) ns "
        f"({total_in} decoded) in {seconds:.1f} s -> {out}")
    return {"out": str(out), "views": counts, "t_start": start, "t_end": end, "window_source": window_source,
            "offsets_source": offsets_source, "events": total_out, "events_decoded": total_in, "seconds": seconds,
            "width": W, "height": H}


def _stream_view(v: ViewRecord, offset: int, topic: str, start: int, end: int | None, s: int, W0: int, H0: int,
                 vw, rate: _RateHistogram | None, batch_events: int, crop=None, sensor=None) -> dict:
    """One pass over the view's event topic: shift, crop, downsample, append."""
    from ..io.rosbag2 import open_bag

    stats = {"events_decoded": 0, "events_in_window": 0, "dropped_odd_edge": 0, "outside_crop": 0, "first_t": None,
             "last_t": None}
    sensor = (W0, H0) if sensor is None else tuple(sensor)      # the camera's size (W0, H0: after the crop)
    odd = s > 1 and (W0 % s or H0 % s)
    pending: list[np.ndarray] = []
    n_pending = 0
    done = False

    def flush():
        nonlocal pending, n_pending, done
        if not pending:
            return
        ev = np.concatenate(pending)            # our own copy: safe to modify in place
        pending, n_pending = [], 0
        t = ev["t"]
        t -= offset
        prev = stats["last_t"]
        if prev is not None and int(t[0]) < prev:
            raise FormatError(f"events go back in time at t={int(t[0]) + offset} ns (view clock) after "
                              f"{prev + offset} ns; the event stream must be sorted")
        if stats["first_t"] is None:
            stats["first_t"] = int(t[0])
        stats["last_t"] = int(t[-1])
        back = np.flatnonzero(t[1:] < t[:-1])
        if back.size:
            j = int(back[0]) + 1
            raise FormatError(f"events go back in time at t={int(t[j]) + offset} ns (view clock) after "
                              f"{int(t[j - 1]) + offset} ns; the event stream must be sorted")
        if rate is not None:                    # after the order check: bins assume sorted times
            rate.add(t)
        i0 = int(np.searchsorted(t, start, "left"))
        i1 = ev.size if end is None else int(np.searchsorted(t, end, "left"))
        if end is not None and i1 < ev.size:
            done = True
        ev = ev[i0:i1]
        if crop is not None and ev.size:       # the sensor window, then its own pixel grid
            x0, y0 = crop[0], crop[1]
            keep = (ev["x"] >= x0) & (ev["x"] < x0 + W0) & (ev["y"] >= y0) & (ev["y"] < y0 + H0)
            stats["outside_crop"] += int(ev.size - np.count_nonzero(keep))
            ev = ev[keep]
            ev["x"] -= np.uint16(x0)
            ev["y"] -= np.uint16(y0)
        if s > 1 and ev.size:
            if odd:
                keep = (ev["x"] < W0 - W0 % s) & (ev["y"] < H0 - H0 % s)
                stats["dropped_odd_edge"] += int(ev.size - np.count_nonzero(keep))
                ev = ev[keep]
            ev["x"] //= s
            ev["y"] //= s
        stats["events_in_window"] += int(ev.size)
        sink.append(ev)

    sink = _BackgroundAppender(vw)
    try:
        with open_bag(v.bag) as bag:
            for pk in bag.iter_event_packets(topic):
                if (pk.width, pk.height) != sensor:
                    raise InputError(f"the event stream is {pk.width}x{pk.height} but session.yaml's camera is "
                                     f"{sensor[0]}x{sensor[1]}; every view must have the session's resolution")
                if pk.events.size:
                    pending.append(pk.events)
                    n_pending += pk.events.size
                    stats["events_decoded"] += int(pk.events.size)
                if n_pending >= batch_events:
                    flush()
                    if done:
                        break
            flush()
    except BaseException:
        sink.close(raise_error=False)
        raise
    sink.close()
    return stats


class _BackgroundAppender:
    """Appends batches to a training-set view in a second thread: HDF5 compresses and writes
    with the GIL released, so writing overlaps decoding (two cores). At most `depth` batches
    wait in the queue (bounded memory); an error in the writer is raised in the caller at
    the next append or at close. Whatever interrupts the caller (Ctrl-C, SIGTERM), the
    writer has stopped before close returns or raises: the file is never closed under it."""

    def __init__(self, view_writer, depth: int = 2):
        import queue
        import threading

        self.vw = view_writer
        self.exc: BaseException | None = None
        self.cancelled = threading.Event()
        # set by the writer as it leaves; Thread.join/is_alive cannot be trusted once a join
        # was interrupted (CPython < 3.13 may then report a running thread as stopped)
        self.stopped = threading.Event()
        self.q = queue.Queue(maxsize=depth)
        self.thread = threading.Thread(target=self._run, name="convert-writer", daemon=True)
        self.thread.start()

    def _run(self):
        try:
            while not self.cancelled.is_set():
                item = self.q.get()
                if item is None:
                    return
                if self.exc is None and not self.cancelled.is_set():
                    try:
                        self.vw.append(item)
                    except BaseException as exc:  # noqa: BLE001 - handed to the caller
                        self.exc = exc
        finally:
            self.stopped.set()

    def append(self, events) -> None:
        if self.exc is not None:
            raise self.exc
        self.q.put(events)

    def close(self, *, raise_error: bool = True) -> None:
        """Write what is queued and stop the writer; on an error or interrupt, drop it instead."""
        if not raise_error:
            self._stop_now()
            return
        try:
            self.q.put(None)
            self.stopped.wait()
        except BaseException:
            self._stop_now()
            raise
        if self.exc is not None:
            raise self.exc

    def _stop_now(self) -> None:
        """Cancel and wait for the writer to leave HDF5, even through further interrupts."""
        import queue

        self.cancelled.set()
        while not self.stopped.is_set():
            try:
                self.q.put_nowait(None)            # wakes a writer waiting for work
            except queue.Full:
                pass
            try:
                self.stopped.wait(0.05)
            except BaseException:  # noqa: BLE001 - a second Ctrl-C must not leave it writing
                continue


# =========================================================================== entry points


def _twin_frame_ns(session) -> int | None:
    """``rig.virtual.frame_ns`` of a virtual-rig capture (the camera twin's render period), or
    None; anything but a whole number of ns > 0 is refused."""
    frame_ns = ((session.data.get("rig") or {}).get("virtual") or {}).get("frame_ns")
    if frame_ns is not None and (isinstance(frame_ns, bool) or not isinstance(frame_ns, int) or frame_ns <= 0):
        raise InputError(f"{session_yaml_path(session.root)}: rig.virtual.frame_ns must be a whole number of ns "
                         f"> 0 (the camera twin's render period), got {frame_ns!r}")
    return frame_ns


def _truth_record(source: dict | None, views: dict, options: dict | None, *,
                  frame_ns=None, servo_tracks: dict | None = None) -> tuple[dict | None, str]:
    """What evaluation needs to render the true scene (evdnerf_ros.eval.truth), or (None, why
    not; "" for a session that does not know its scene, e.g. a real capture). Two kinds of
    session know it: a simulated one (rendered at options.supersample) and one captured on the
    virtual rig (``source.rig: virtual``; its camera twin rendered ``source.scene_ref`` at
    ``source.supersample``). Both write ``ground_truth.clock_offset_ns`` as the view clock's
    reading at scene time 0 (the view clock reads scene time + clock offset), so the scene time
    at the common origin is offset - clock offset, whichever way the offsets were found.
    The twin rendered only every ``frame_ns`` of its sensor clock (``rig.virtual.frame_ns``),
    joined linearly in log; with every view's ``ground_truth.sensor_zero_scene_ns`` that grid
    goes into the record as ``render_grid`` (period, and per view the scene time of a grid
    point), so that the reference renders what the twin did; so do the servo angles the twin
    rendered (``servo_tracks``: per view ``ground_truth.servo_track``, scene time), where every
    view has them."""
    source = source or {}
    kind = source.get("kind")
    if kind == "simulation":
        supersample = (options or {}).get("supersample", 2)
    elif kind == "capture" and source.get("rig") == "virtual":
        supersample = source.get("supersample", 1)
    else:
        return None, ""
    if not source.get("scene_ref"):
        return None, ""
    unknown = [name for name, v in views.items() if v.get("ground_truth_clock_offset_ns") is None]
    if unknown:
        fix = ("the virtual rig records none where its camera twin placed the trigger edge late or not at all, "
               "when the machine fell behind real time: capture again on a less loaded machine"
               if kind == "capture" else "restore the simulator's ground_truth records in session.yaml")
        which = f"view{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}"
        return None, (f"no true scene: session.yaml has no ground_truth.clock_offset_ns for {which}, so the "
                      f"scene's time there is unknown ({fix})")
    stale = {name: int(v["ground_truth_stale_renders"]) for name, v in views.items()
             if v.get("ground_truth_stale_renders")}
    if stale:
        which = ", ".join(f"{name} ({n})" for name, n in stale.items())
        return None, (f"no true scene: the virtual rig's camera twin rendered chunks of view(s) {which} with stale joint "
                      "angles (the harness fell behind real time), so their events are not the scene's: capture again "
                      "on a less loaded machine")
    origin = {name: int(v["offset_ns"]) - int(v["ground_truth_clock_offset_ns"]) for name, v in views.items()}
    record = {"scene": str(source["scene_ref"]), "supersample": int(supersample),
              "scene_time_at_origin_ns": origin}
    zeros = {name: v.get("ground_truth_sensor_zero_scene_ns") for name, v in views.items()}
    if kind == "capture" and frame_ns and all(z is not None for z in zeros.values()):
        record["render_grid"] = {"period_ns": int(frame_ns),
                                 "scene_ns": {name: int(z) for name, z in zeros.items()}}
    tracks = {name: (servo_tracks or {}).get(name) for name in views}
    if kind == "capture" and all(tracks.values()):
        record["servo_tracks"] = tracks
    return record, ""


def _joint_record(servo: dict | None, truth: dict) -> dict | None:
    """The servo's joint on the common clock (the ``hinge`` field's, ``train.joint``): session.yaml's
    axis, pivot and angle samples, and the servo's start = its scene time minus the scene time at
    the common origin (the views' median: they agree up to the sync error). Only where the
    session records the joint and the scene's clock (simulated and virtual-rig sessions): a real
    capture would time the start by its trigger edges (not built)."""
    if not servo or servo.get("angle_rad") is None or servo.get("start_ns_scene") is None:
        return None
    origin = int(np.median([int(v) for v in truth["scene_time_at_origin_ns"].values()]))
    return {"axis": [float(v) for v in servo["axis"]], "pivot": [float(v) for v in servo["pivot"]],
            "start_ns": int(servo["start_ns_scene"]) - origin, "step_ns": int(servo["angle_rad"]["step_ns"]),
            "angles_rad": [float(v) for v in servo["angle_rad"]["values"]]}


def run_convert(session_dir, out, options: ConvertOptions | None = None, *, overwrite: bool = False,
                log=print, **fields) -> dict:
    """`evdnerf convert SESSION -o OUT [--format h5|evdnerf]`: a training set .h5 (fmt="h5") or
    a folder in the EvDNeRF paper's format (fmt="evdnerf", see
    :func:`evdnerf_ros.io.evdnerf_format.export_evdnerf`; ``raw_events=False`` skips their
    per-view (N, 4) int64 event arrays, which are built in memory one view at a time at 32
    bytes per event). `fields` replace single options. Returns a summary dict."""
    options = replace(options or ConvertOptions(), **fields)
    if options.window is not None:
        options = replace(options, window=tuple(options.window))
    if options.scene_bounds is not None:
        options = replace(options, scene_bounds=tuple(map(tuple, options.scene_bounds)))
    options.check()
    if options.fmt == "h5":
        return convert_session(session_dir, out, options, overwrite=overwrite, log=log)
    from ..io.evdnerf_format import export_evdnerf

    out = Path(out)
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise OutputExistsError(out)
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"{out}: parent folder {parent} does not exist; create it first")
    # named like the atomic helper's temporaries, so that a killed run's leftover is found and
    # removed by the next run writing `out`
    with tempfile.TemporaryDirectory(prefix=f".{out.name}.{os.getpid()}.", suffix=PARTIAL_SUFFIX, dir=parent) as td:
        h5 = Path(td) / "train.h5"
        summary = convert_session(session_dir, h5, options, log=log)
        summary["export"] = export_evdnerf(h5, out, n_windows=options.n_windows, event_time=options.event_time,
                                           events=options.raw_events, overwrite=overwrite, log=log)
    summary["out"] = str(out)
    return summary
