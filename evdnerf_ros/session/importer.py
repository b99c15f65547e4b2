"""`evdnerf import-bags BAG... -o SESSION`: a capture session from bags recorded without this
toolkit (metavision_driver, libcaer_driver, `ros2 bag record` of dvs_msgs), so that sync,
convert and train work on them.

Inputs
------
Anything :func:`evdnerf_ros.io.bag_reader.open_bag` opens (a rosbag2 folder, a bare .mcap or
.db3, a ROS 1 .bag) whose event topic is an ``event_camera_msgs/msg/EventPacket`` (evt3, evt2,
mono, libcaer, libcaer_cmp) or a ``dvs_msgs/msg/EventArray``. The event topic is ``topic``
or the bag's only event topic (:func:`~evdnerf_ros.io.bag_reader.pick_event_topic`).

Views
-----
- One bag per view (default): view ``view_00`` is the first bag, and so on. An EventPacket
  topic of a rosbag2 is **passed through**: every message is copied byte for byte with its
  bag time (a ROS 1 bag's messages get a ROS 2 CDR envelope around the same payload bytes,
  stamp, seq and time_base), so the imported view decodes to exactly the events of the
  input. A dvs_msgs EventArray topic is re-encoded (below).
- ``split_at="triggers"``: ONE bag cut into views at its EXT_TRIGGER edges (``trigger_edge``
  rising by default, optionally one ``trigger_id``), read from the event stream or from
  ``trigger_topic`` (another event topic carrying the trigger stream).
  ``split_at="servo-start"``: cut at the servo firmware's START messages
  (``sensor_msgs/msg/TimeReference`` on ``servo_topic``, source ``... START``, as the
  recorder writes them; the cut is the header stamp). With cuts c_0 < ... < c_{N-1}, view k
  holds the times [c_k - pre, c_{k+1} - pre), where pre = min(``pre_roll_ns``, half the
  shortest gap between cuts), view 0 starting at the beginning of the bag and the last view
  ending at its end: nothing is dropped, every view holds its cut and a quiet stretch before
  it (what sync's trigger / START / rate methods look for). ``views`` N checks the count.
  Split views are re-encoded: an evt3 stream cut between two packets loses the decoder
  state (time high bits, row) its bytes depend on, and a cut falls inside packets.
- Re-encoding keeps the source's EventPacket encoding when the times allow it (all times on
  one microsecond grid for evt3 / evt2 / libcaer / libcaer_cmp, the sensor within that
  encoding's size); otherwise evt3 (dvs_msgs arrays on a microsecond grid), else ``mono``
  (nanosecond-exact). Trigger edges ride along in evt3 / evt2. Event times are never changed:
  each view keeps its own clock (``evdnerf sync`` aligns them).

Servo messages of the input (START / DONE TimeReference on ``servo_topic``, JointState on
``joint_topic``) are copied into the view whose time range holds their stamp.

Intrinsics, poses, thresholds
-----------------------------
Intrinsics, first found: ``calibration`` FILE (ROS camera_calibration / OpenCV camera_info
YAML: image_width, image_height, camera_matrix.data, distortion_model,
distortion_coefficients.data; or our own layout: width, height, K, D, distortion_model, also
under a ``camera:`` key as in session.yaml), the bag's CameraInfo (the only
``sensor_msgs/msg/CameraInfo`` topic, or ``camera_info_topic``; an all-zero K, as uncalibrated
drivers publish, counts as none), ``fov_deg`` (nominal pinhole, centred; a warning), else
unknown: camera.K is then a placeholder of :data:`PLACEHOLDER_FOV_DEG` degrees, session.yaml
says so (``camera.intrinsics_source: unknown``, ``source.calibration``) and a warning says the
session is good for sync only. Poses: ``poses`` FILE (YAML / JSON: a list, or ``poses:`` a
list, or ``views:`` a list of ``{T_world_cam}`` as `evdnerf calibrate` writes, with one entry
per view: a 4x4 ``T_world_cam`` matrix, or ``{position: [x, y, z], orientation: [x, y, z, w]}``;
optional ``azimuth_deg``), or ``ring`` RADIUS (the simulator's
ring, :func:`evdnerf_ros.geometry.camera.ring_poses`: N views evenly over 360 degrees at
``ring_elevation_deg``, looking at the origin, from azimuth ``ring_offset_deg``), else the
identity for a single view (several views without poses are refused). Thresholds: ``c_pos``
/ ``c_neg`` (nominal default :data:`~evdnerf_ros.io.evdnerf_format.DEFAULT_THRESHOLD`, the
paper's; session.yaml's ``thresholds.source`` says whether they were given).

Output
------
The session (session.yaml with ``source.kind: import`` and, per input, its path, topic, message
type, encoding, storage, size, message / event / trigger counts and time ranges; one rosbag2
per view in the standard topics) is written through :mod:`.recorder` into a temporary folder
renamed into place at the end (:func:`evdnerf_ros.atomic.atomic_output`): on any error nothing
is left. Decoding is streamed in batches (bounded memory); a split reads the bag twice.

Errors (InputError, one line naming the file / topic and the fix): no event topic, several
without ``topic``, an event topic without messages or events, a split finding another number of
cuts than ``views`` (or none), a split of several bags, resolutions that differ across bags or
from the calibration, poses of the wrong count, a bad calibration or poses file.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import atomic_output, check_output
from ..errors import InputError
from ..events.types import MAX_SENSOR_SIZE
from ..geometry.camera import CameraRing, PinholeCamera, ring_poses
from ..geometry.poses import check_rigid
from ..io.evdnerf_format import DEFAULT_THRESHOLD
from ..options import check_value, flag_name, option, option_fields
from ..topics import SERVO_JOINT_STATES, SERVO_TRIGGER
from ..yamlcheck import Where, is_number, load_yaml, mapping, matrix, number_in
from .recorder import (SERVO_EVENTS, ViewRecorder, camera_record, servo_record, session_document,
                       view_record, write_session_yaml)

SPLITS = ("triggers", "servo-start")
EDGES = ("rising", "falling")
STORAGES = ("mcap", "sqlite3")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
#: camera.K of a session whose calibration is unknown (sync only): a nominal field of view.
PLACEHOLDER_FOV_DEG = 90.0
#: Re-encoding: the largest sensor each EventPacket encoding carries (packetizer's limits).
_ENCODING_SIZE = {"evt3": (MAX_SENSOR_SIZE, MAX_SENSOR_SIZE), "evt2": (MAX_SENSOR_SIZE, MAX_SENSOR_SIZE),
                  "libcaer": (1 << 15, 1 << 15), "libcaer_cmp": (1 << 11, 1 << 11), "mono": (1 << 16, 1 << 15)}
_GRID_ENCODINGS = ("evt3", "evt2", "libcaer", "libcaer_cmp")


class SessionImportWarning(UserWarning):
    """Something the imported session lacks (calibration, nominal intrinsics)."""


@dataclass(frozen=True)
class ImportOptions:
    """Every knob of `evdnerf import-bags` (defaults in one place; module doc)."""

    topic: str | None = option(None, "event topic of the bags", kind=str, none_help="the bag's only event topic")
    split_at: str | None = option(None, "cut ONE bag into views at its trigger edges or servo START messages",
                                  kind=str, choices=SPLITS, none_help="one bag per view")
    views: int | None = option(None, "expected number of views (a split finding another count is an error)",
                               kind=int, low=1, high=100_000, none_help="no check")
    trigger_edge: str = option("rising", "--split-at triggers: the edge that cuts", choices=EDGES)
    trigger_id: int | None = option(None, "--split-at triggers: EXT_TRIGGER channel", kind=int, low=0, high=255,
                                    none_help="any")
    trigger_topic: str | None = option(None, "--split-at triggers: event topic carrying the trigger stream",
                                       kind=str, none_help="the event topic")
    servo_topic: str = option(SERVO_TRIGGER, "servo START/DONE TimeReference topic (copied; --split-at "
                                             "servo-start cuts at START)")
    joint_topic: str = option(SERVO_JOINT_STATES, "servo JointState topic (copied)")
    pre_roll_ns: int = option(100_000_000, "split views start this long before their cut (at most half the "
                                           "shortest gap)", flag="--pre-roll", duration=True, low=0,
                              high=3_600 * 10**9)
    calibration: str | None = option(None, "intrinsics YAML (ROS camera_calibration / OpenCV camera_info "
                                           "layout, or width/height/K/D)", kind=str,
                                     none_help="the bag's CameraInfo")
    camera_info_topic: str | None = option(None, "CameraInfo topic of the bags", kind=str,
                                           none_help="the bag's only CameraInfo topic")
    fov_deg: float | None = option(None, "nominal horizontal field of view when there is no calibration",
                                   flag="--fov", kind=float, low=0, low_open=True, high=179.9,
                                   none_help="calibration unknown")
    poses: str | None = option(None, "per-view poses file (YAML/JSON: 4x4 T_world_cam or position + "
                                     "orientation xyzw)", kind=str, none_help="--ring, or identity for one view")
    ring: float | None = option(None, "poses on a camera ring of this radius (m) around the origin",
                                kind=float, low=0, low_open=True, high=1e6, none_help="no ring")
    ring_elevation_deg: float = option(CameraRing.elevation_deg, "--ring: elevation (deg)", low=-89, high=89)
    ring_offset_deg: float = option(0.0, "--ring: azimuth of the first view (deg)", low=-360, high=360)
    c_pos: float = option(DEFAULT_THRESHOLD, "contrast threshold C+ for session.yaml", low=0, low_open=True,
                          high=10)
    c_neg: float = option(DEFAULT_THRESHOLD, "contrast threshold C- for session.yaml", low=0, low_open=True,
                          high=10)
    storage: str = option("mcap", "storage of the view bags", choices=STORAGES)

    def check(self) -> None:
        for f, spec in option_fields(ImportOptions):
            check_value(getattr(self, f.name), f, spec, f"import-bags: {flag_name(f, spec)}")
        for name in ("topic", "trigger_topic", "servo_topic", "joint_topic", "camera_info_topic"):
            value = getattr(self, name)
            if value is not None and not value.startswith("/"):
                raise InputError(f"import-bags: --{name.replace('_', '-')} {value!r}: give an absolute topic "
                                 "name such as /event_camera/events")
        if self.poses is not None and self.ring is not None:
            raise InputError("import-bags: --poses and --ring both give the poses; choose one")


# =========================================================================== inputs


@dataclass
class _Input:
    path: Path
    topic: str
    msgtype: str
    storage: str
    ros1: bool
    width: int
    height: int
    encoding: str                  # EventPacket encoding, or "array" (dvs_msgs)
    messages: int
    bag_start_ns: int
    bag_end_ns: int
    intrinsics: dict | None        # from the bag's CameraInfo
    camera_info_topic: str | None
    servo: tuple                   # _servo_messages()


def _first_fields(bag, topic: str, what: str):
    from ..io import event_messages as em
    from ..io.typestore import DVS_EVENT_ARRAY

    for m in bag.messages(topic):
        if m.msgtype == DVS_EVENT_ARRAY:
            f = em.event_array_layout(m.data, ros1=bag.ros1, what=what)
            return int(f.width), int(f.height), "array"
        f = em.parse_event_packet(m.data, ros1=bag.ros1, what=what)
        return int(f.width), int(f.height), str(f.encoding)
    raise InputError(f"{what} has no messages; import a bag with a recorded event stream")


def _camera_info(bag, options: ImportOptions) -> tuple[dict | None, str | None]:
    """The bag's CameraInfo intrinsics (None when it has none, or an all-zero K)."""
    if options.camera_info_topic is not None:
        bag.topic(options.camera_info_topic)          # lists the topics when it is missing
        topic = options.camera_info_topic
    else:
        found = [n for n, t in bag.topics.items() if t.msgtype == CAMERA_INFO_TYPE]
        if not found:
            return None, None
        if len(found) > 1:
            raise InputError(f"{bag.path}: the bag has {len(found)} CameraInfo topics ({', '.join(found)}); "
                             "choose one with --camera-info-topic")
        topic = found[0]
    for _, msg in bag.read_messages(topic):
        # ROS 2 fields are d / k; a ROS 1 bag's are D / K
        K = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), np.float64).reshape(-1)
        D = np.asarray(getattr(msg, "d", getattr(msg, "D", [])), np.float64).reshape(-1)
        if K.size != 9 or not np.any(K):
            return None, topic
        return {"width": int(msg.width), "height": int(msg.height), "K": K.reshape(3, 3), "D": D,
                "distortion_model": str(msg.distortion_model) or "plumb_bob",
                "source": f"CameraInfo {topic} of {bag.path}"}, topic
    return None, topic


def _probe(path: Path, options: ImportOptions) -> _Input:
    from ..io.bag_reader import open_bag, pick_event_topic

    with open_bag(path) as bag:
        topic = pick_event_topic(bag, options.topic)
        info = bag.topic(topic)
        what = f"{path}: topic {topic}"
        from ..io.packetizer import EVENT_TYPES

        if info.msgtype not in EVENT_TYPES:
            raise InputError(f"{what} has type {info.msgtype}, not an event type ({', '.join(EVENT_TYPES)}); "
                             "name the event topic with --topic")
        if info.message_count == 0:
            raise InputError(f"{what} has no messages (an empty recording); import a bag that holds events")
        width, height, encoding = _first_fields(bag, topic, what)
        intr, ci_topic = _camera_info(bag, options)
        servo = _servo_messages(bag, options)
        return _Input(path=path, topic=topic, msgtype=str(info.msgtype), storage=bag.storage, ros1=bag.ros1,
                      width=width, height=height, encoding=encoding, messages=info.message_count,
                      bag_start_ns=int(bag.start_ns), bag_end_ns=int(bag.end_ns), intrinsics=intr,
                      camera_info_topic=ci_topic, servo=servo)


# =========================================================================== calibration / poses


def read_calibration(path) -> dict:
    """Intrinsics from a calibration YAML (module doc): {width, height, K, D, distortion_model}."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such calibration file")
    data = load_yaml(path, what="calibration file", empty="expected image_width, image_height, "
                                                         "camera_matrix, distortion_coefficients")
    top = Where(path)
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping (ROS camera_info YAML: image_width, image_height, "
                         "camera_matrix, distortion_coefficients)")
    if "camera_matrix" in data:          # ROS camera_calibration / OpenCV camera_info YAML
        width = number_in(data, "image_width", top, integer=True, low=1, high=65535)
        height = number_in(data, "image_height", top, integer=True, low=1, high=65535)
        cm = mapping(data["camera_matrix"], top / "camera_matrix")
        Kd = cm.get("data")
        if not isinstance(Kd, list) or len(Kd) != 9 or not all(is_number(v) for v in Kd):
            (top / "camera_matrix" / "data").fail("must be a list of 9 numbers (K, row-major)")
        K = np.asarray(Kd, np.float64).reshape(3, 3)
        dist = data.get("distortion_coefficients")
        D = [] if dist is None else mapping(dist, top / "distortion_coefficients").get("data", [])
        where_d = top / "distortion_coefficients" / "data"
    else:                                # our layout (optionally under camera:, as in session.yaml)
        sec = data.get("camera", data)
        where = top / "camera" if "camera" in data else top
        sec = mapping(sec, where)
        width = number_in(sec, "width", where, integer=True, low=1, high=65535)
        height = number_in(sec, "height", where, integer=True, low=1, high=65535)
        if sec.get("K") is None:
            raise InputError(f"{path}: not a calibration file: expected image_width, image_height, camera_matrix "
                             "(ROS camera_info YAML) or width, height, K, D")
        K = matrix(sec.get("K"), (3, 3), where / "K")
        D = sec.get("D", [])
        where_d, data = where / "D", sec
    if not isinstance(D, list) or len(D) > 14 or not all(is_number(v) for v in D):
        where_d.fail("must be a list of at most 14 numbers (distortion coefficients)")
    D = np.asarray(D, np.float64)
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(D)):
        raise InputError(f"{path}: K or the distortion holds NaN or inf; fix the calibration file")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.array_equal(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise InputError(f"{path}: K {K.tolist()} is not a pinhole intrinsic matrix (fx, fy > 0, "
                         "K[1,0] = 0, last row [0, 0, 1]); fix the calibration file")
    model = data.get("distortion_model") or "plumb_bob"
    if not isinstance(model, str):
        (top / "distortion_model").fail(f"must be a name such as 'plumb_bob', got {model!r}")
    return {"width": int(width), "height": int(height), "K": K, "D": D, "distortion_model": model,
            "source": f"calibration file {path}"}


def _distortion(intr: dict) -> tuple[np.ndarray, str]:
    """(D, model) as CameraInfo takes them: plumb_bob with fewer than 5 coefficients is padded."""
    from ..io.messages import DISTORTION_SIZES

    D, model = np.asarray(intr["D"], np.float64), intr["distortion_model"]
    need = DISTORTION_SIZES.get(model)
    if need is not None and D.size < need and not np.any(D[need:]):
        D = np.concatenate([D, np.zeros(need - D.size)])
    if need is not None and D.size != need:
        raise InputError(f"{intr['source']}: distortion model {model!r} takes {need} coefficients, got {D.size}; "
                         "fix the calibration")
    return D, model


def _read_poses(path, n: int) -> tuple[list[np.ndarray], list[float | None]]:
    from ..io.poses import extrinsics

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such poses file")
    data = load_yaml(path, what="poses file", empty="expected one pose per view")
    top = Where(path)
    if isinstance(data, dict):          # poses: [...], or the views: [{T_world_cam}] of `evdnerf calibrate`
        key = "poses" if "poses" in data or "views" not in data else "views"
        data, top = data.get(key), top / key
    if not isinstance(data, list):
        raise InputError(f"{top}: expected a list with one pose per view (a 4x4 T_world_cam, or position + "
                         "orientation [x, y, z, w])")
    if len(data) != n:
        raise InputError(f"{top}: {len(data)} poses for {n} views; give one pose per view, in view order")
    poses, azimuths = [], []
    for i, entry in enumerate(data):
        w = top / i
        az = None
        if isinstance(entry, dict):
            az = number_in(entry, "azimuth_deg", w, required=False, low=-1e6, high=1e6)
            if entry.get("T_world_cam") is not None:
                T = matrix(entry["T_world_cam"], (4, 4), w / "T_world_cam")
            elif entry.get("position") is not None and entry.get("orientation") is not None:
                o = entry["orientation"]
                if isinstance(o, dict):
                    o = [o.get(k) for k in ("x", "y", "z", "w")]
                if not (isinstance(entry["position"], list) and isinstance(o, list)
                        and all(is_number(v) for v in entry["position"] + o)):
                    w.fail("position must be 3 numbers and orientation 4 (x, y, z, w)")
                try:
                    T = extrinsics(entry["position"], quat_xyzw=o, what=str(w))
                except InputError as exc:
                    raise InputError(str(exc)) from None
            else:
                w.fail("needs T_world_cam (4x4), or position [x, y, z] and orientation [x, y, z, w]")
        else:
            T = matrix(entry, (4, 4), w)
        try:
            poses.append(check_rigid(T, f"{w}"))
        except InputError as exc:
            raise InputError(f"{exc}; give a rotation with det +1 and last row [0, 0, 0, 1]") from None
        azimuths.append(None if az is None else float(az))
    return poses, azimuths


# =========================================================================== splits


def _edges(tr: np.ndarray, options: ImportOptions) -> np.ndarray:
    """Times of the trigger edges that cut (--trigger-edge, --trigger-id)."""
    sel = tr["value"] == (1 if options.trigger_edge == "rising" else 0)
    if options.trigger_id is not None:
        sel &= tr["id"] == options.trigger_id
    return tr["t"][sel]


def _trigger_cuts(path: Path, topic: str, options: ImportOptions) -> np.ndarray:
    """The cutting edges of another event topic carrying the trigger stream (--trigger-topic)."""
    from ..io.bag_reader import open_bag, TopicDecoder

    cuts = [np.empty(0, np.int64)]
    with open_bag(path) as bag:
        dec = TopicDecoder(bag, topic)
        for _, tr in _batches(bag, topic, dec):
            cuts.append(_edges(tr, options))
    return np.unique(np.concatenate(cuts))


def _servo_messages(bag, options: ImportOptions) -> tuple[list, list]:
    """(START/DONE: [(stamp, what, device_ns)], joints: [(stamp, names, positions)]) of an open bag."""
    from ..io.messages import header_stamp_ns, time_reference_ns

    starts, joints = [], []
    topics = bag.topics
    t = topics.get(options.servo_topic)
    if t is not None and t.msgtype == "sensor_msgs/msg/TimeReference":
        for _, msg in bag.read_messages(options.servo_topic):
            stamp, ref, source = time_reference_ns(msg)
            words = source.replace(":", " ").split()
            what = next((w for w in reversed(words) if w in SERVO_EVENTS), None)
            if what is not None:
                starts.append((int(stamp), what, int(ref)))
    t = topics.get(options.joint_topic)
    if t is not None and t.msgtype == "sensor_msgs/msg/JointState":
        for _, msg in bag.read_messages(options.joint_topic):
            names = [str(n) for n in msg.name]
            pos = np.asarray(msg.position, np.float64)
            if names and pos.size == len(names):
                joints.append((header_stamp_ns(msg), names, pos))
    return starts, joints


def _view_bounds(cuts: np.ndarray, pre_roll_ns: int) -> tuple[np.ndarray, int]:
    """Inner boundaries [c_k - pre for k >= 1] and the pre-roll used (module doc)."""
    pre = int(pre_roll_ns)
    if cuts.size > 1:
        pre = min(pre, int(np.diff(cuts).min()) // 2)
    return cuts[1:] - pre, pre


# =========================================================================== writing


def _batches(bag, topic, dec):
    """Whole-topic batched decode: (events, triggers) per batch, then the decoder's tail."""
    for m in bag.messages(topic):
        out = dec.add(m)
        if out is not None:
            yield out
    yield dec.flush()
    yield dec.close()


class _Stats:
    def __init__(self):
        self.events = self.triggers = 0
        self.first = self.last = None
        self.residues: set[int] = set()

    def add(self, ev, tr):
        self.events += int(ev.size)
        self.triggers += int(tr.size)
        for a in (ev, tr):
            if a.size:
                lo, hi = int(a["t"][0]), int(a["t"][-1])
                self.first = lo if self.first is None else min(self.first, lo)
                self.last = hi if self.last is None else max(self.last, hi)
                if len(self.residues) < 2:
                    self.residues.update(np.unique(a["t"] % 1000).tolist())

    def record(self) -> dict:
        return {"events": self.events, "trigger_events": self.triggers, "first_ns": self.first,
                "last_ns": self.last}


def _target_encoding(inp: _Input, stats: _Stats) -> str:
    """The encoding re-encoded views are written in (module doc)."""
    one_grid = len(stats.residues) <= 1
    candidates = ([inp.encoding] if inp.encoding != "array" else []) + ["evt3", "mono"]
    for enc in candidates:
        if stats.triggers and enc not in ("evt3", "evt2"):
            continue
        wmax, hmax = _ENCODING_SIZE[enc]
        if inp.width > wmax or inp.height > hmax:
            continue
        if enc in _GRID_ENCODINGS and not one_grid:
            continue
        return enc
    raise InputError(f"{inp.path}: topic {inp.topic}: its {stats.triggers} trigger edges need encoding evt3, but "
                     f"the times are not on one microsecond grid or the sensor ({inp.width}x{inp.height}) is "
                     f"larger than evt3 carries ({MAX_SENSOR_SIZE}); import without --split-at triggers")


def _to_cdr(data, what: str) -> bytes:
    """A ROS 1 EventPacket as ROS 2 CDR: the same payload bytes, stamp, seq, time_base, frame_id."""
    from ..io import event_messages as em

    f = em.parse_event_packet(data, ros1=True, what=what)
    prefix = em.CdrEventPacketPrefix(f.frame_id, f.height, f.width, f.encoding, f.is_bigendian)
    payload = bytes(f.events)
    return prefix(f.stamp_ns, f.seq, f.time_base, len(payload)) + payload


@dataclass
class _ViewPlan:
    name: str
    source: int                         # index of the input
    lo: int | None                      # [lo, hi) of the input's times (None: open)
    hi: int | None
    T_world_cam: np.ndarray = None
    azimuth_deg: float | None = None
    cut_ns: int | None = None
    stats: _Stats = field(default_factory=_Stats)
    encoding: str = ""
    passed_through: bool = False
    packets: int = 0


def _in_range(t: int, plan: _ViewPlan) -> bool:
    return (plan.lo is None or t >= plan.lo) and (plan.hi is None or t < plan.hi)


def _open_view(root: Path, plan: _ViewPlan, inp: _Input, camera: dict, options: ImportOptions, servo) -> ViewRecorder:
    rec = ViewRecorder(root / plan.name, width=inp.width, height=inp.height, encoding=plan.encoding,
                       storage=options.storage)
    rec.__enter__()
    try:
        t0 = plan.lo if plan.lo is not None else inp.bag_start_ns
        t0 = max(int(t0), 0)
        rec.camera_info(camera["K"], camera["D"], stamp_ns=t0, distortion_model=camera["distortion_model"])
        rec.pose(plan.T_world_cam, t0)
        starts, joints = servo
        for stamp, what, ref in starts:
            if _in_range(stamp, plan):
                rec.servo_trigger(what, stamp, ref)
        for stamp, names, pos in joints:
            if _in_range(stamp, plan):
                rec.servo_joint_state(names, pos, stamp)
    except BaseException as exc:
        rec.__exit__(type(exc), exc, exc.__traceback__)
        raise
    return rec


def _write_passthrough(root, plan: _ViewPlan, inp: _Input, camera, options, servo) -> None:
    from ..io.bag_reader import TopicDecoder, open_bag

    with open_bag(inp.path) as bag:
        dec = TopicDecoder(bag, inp.topic)
        rec = _open_view(root, plan, inp, camera, options, servo)
        with _closing(rec):
            for m in bag.messages(inp.topic):
                data = _to_cdr(m.data, f"{inp.path}: topic {inp.topic}") if inp.ros1 else m.data
                rec.event_packet(data, m.t_ns)
                plan.packets += 1
                out = dec.add(m)
                if out is not None:
                    plan.stats.add(*out)
            plan.stats.add(*dec.flush())
            plan.stats.add(*dec.close())


class _closing:
    """Close a ViewRecorder opened by _open_view (abort it on an error)."""

    def __init__(self, rec):
        self.rec = rec

    def __enter__(self):
        return self.rec

    def __exit__(self, exc_type, exc, tb):
        return self.rec.__exit__(exc_type, exc, tb)


def _write_reencoded(root, plans: list[_ViewPlan], inp: _Input, camera, options, servo) -> None:
    """Decode the input once more and write each view's time range (plans in time order)."""
    from ..io.bag_reader import TopicDecoder, open_bag

    bounds = np.array([p.hi for p in plans[:-1]], np.int64)
    current = {"k": -1, "rec": None}

    def switch(k):
        while current["k"] < k:
            if current["rec"] is not None:
                rec, current["rec"] = current["rec"], None
                rec.__exit__(None, None, None)
            current["k"] += 1
            current["rec"] = _open_view(root, plans[current["k"]], inp, camera, options, servo)

    def route(ev, tr):
        if not ev.size and not tr.size:
            return
        ie = np.searchsorted(ev["t"], bounds, "left")
        it = np.searchsorted(tr["t"], bounds, "left")
        ie = np.concatenate([[0], ie, [ev.size]])
        it = np.concatenate([[0], it, [tr.size]])
        for k in range(len(plans)):
            e, t = ev[ie[k]:ie[k + 1]], tr[it[k]:it[k + 1]]
            if not e.size and not t.size:
                continue
            switch(k)
            plans[k].packets += current["rec"].events(e, t)
            plans[k].stats.add(e, t)

    try:
        with open_bag(inp.path) as bag:
            dec = TopicDecoder(bag, inp.topic)
            for ev, tr in _batches(bag, inp.topic, dec):
                route(ev, tr)
        switch(len(plans) - 1)            # views after the last event still get their bag (checked below)
        rec, current["rec"] = current["rec"], None
        rec.__exit__(None, None, None)
    except BaseException as exc:
        if current["rec"] is not None:
            current["rec"].__exit__(type(exc), exc, exc.__traceback__)
        raise


# =========================================================================== the job


@dataclass
class ImportResult:
    root: Path
    views: list[dict]
    inputs: list[dict]
    events: int
    seconds: float
    warnings: list[str] = field(default_factory=list)


def _warn(msgs: list, text: str) -> None:
    """Note a warning; they are issued once every input is checked (just before writing)."""
    msgs.append(text)


def import_bags(bags, output, options: ImportOptions = ImportOptions(), *, overwrite: bool = False,
                log=None) -> ImportResult:
    """Build the session `output` from `bags` (module doc)."""
    t_start = time.perf_counter()
    options.check()
    say = log or (lambda *_: None)
    paths = [Path(b) for b in (bags or [])]
    if not paths:
        raise InputError("import-bags: no input bags; give one bag per view (or one bag with --split-at)")
    if len(set(p.resolve() for p in paths)) != len(paths):
        raise InputError("import-bags: a bag is given twice; give each view's bag once")
    out = Path(output)
    check_output(out, overwrite=overwrite, directory=True)
    if options.split_at is not None and len(paths) != 1:
        raise InputError(f"import-bags: --split-at {options.split_at} cuts ONE bag into views; got {len(paths)} "
                         "bags (leave --split-at out for one bag per view)")
    if options.split_at is None and options.views is not None and options.views != len(paths):
        raise InputError(f"import-bags: --views {options.views} but {len(paths)} bags given (one bag per view)")
    if options.split_at != "triggers" and options.trigger_topic is not None:
        raise InputError("import-bags: --trigger-topic applies to --split-at triggers only")
    notes: list[str] = []

    inputs = [_probe(p, options) for p in paths]
    first = inputs[0]
    for inp in inputs[1:]:
        if (inp.width, inp.height) != (first.width, first.height):
            raise InputError(f"{inp.path}: topic {inp.topic} is {inp.width}x{inp.height} but {first.path} is "
                             f"{first.width}x{first.height}; a session has one camera: import the bags of one "
                             "sensor (or each resolution as its own session)")
    if first.width == 0 or first.height == 0:
        raise InputError(f"{first.path}: topic {first.topic} declares a {first.width}x{first.height} sensor; "
                         "the session needs its size: re-record with a driver that sets width and height")

    # ----- intrinsics
    width, height = first.width, first.height
    intr, intr_kind = None, "unknown"
    if options.calibration is not None:
        intr, intr_kind = read_calibration(options.calibration), "calibration"
        if options.fov_deg is not None:
            _warn(notes, f"--fov {options.fov_deg:g} ignored: the calibration {options.calibration} gives the "
                         "intrinsics")
    else:
        found = [i for i in inputs if i.intrinsics is not None]
        if found:
            intr, intr_kind = found[0].intrinsics, "camera_info"
            if options.fov_deg is not None:
                _warn(notes, f"--fov {options.fov_deg:g} ignored: {intr['source']} gives the intrinsics")
            for other in found[1:]:
                if not np.allclose(other.intrinsics["K"], intr["K"], rtol=1e-6, atol=1e-9) or \
                        (other.intrinsics["width"], other.intrinsics["height"]) != (intr["width"], intr["height"]):
                    raise InputError(f"{other.path}: its CameraInfo ({other.intrinsics['K'].tolist()}) differs from "
                                     f"{found[0].path}'s ({intr['K'].tolist()}); a session has one camera: give "
                                     "--calibration FILE")
        elif options.fov_deg is not None:
            cam = PinholeCamera.from_fov(width, height, options.fov_deg)
            intr = {"width": width, "height": height, "K": cam.K, "D": np.zeros(5), "distortion_model": "plumb_bob",
                    "source": f"nominal: --fov {options.fov_deg:g} deg, principal point at the centre"}
            intr_kind = "nominal"
            _warn(notes, f"intrinsics are nominal (--fov {options.fov_deg:g} deg, no distortion): the bags have no "
                         "CameraInfo; give --calibration FILE for measured ones")
    if intr is None:
        cam = PinholeCamera.from_fov(width, height, PLACEHOLDER_FOV_DEG)
        intr = {"width": width, "height": height, "K": cam.K, "D": np.zeros(5), "distortion_model": "plumb_bob",
                "source": f"unknown: camera.K is a placeholder ({PLACEHOLDER_FOV_DEG:g} deg field of view); the "
                          "session is good for sync only"}
        _warn(notes, "calibration unknown (no CameraInfo in the bags, no --calibration, no --fov): the session is "
                     "good for `evdnerf sync` only; give --calibration FILE (or --fov DEG) to convert and train")
    if (intr["width"], intr["height"]) != (width, height):
        raise InputError(f"{intr['source']}: {intr['width']}x{intr['height']} but the event stream of {first.path} "
                         f"is {width}x{height}; use the calibration of this sensor at its full resolution")
    D, model = _distortion(intr)
    camera = {"K": np.asarray(intr["K"], np.float64), "D": D, "distortion_model": model}

    # ----- views
    servo_msgs = [inp.servo for inp in inputs]
    split = scan = None
    if options.split_at is None:
        plans = [_ViewPlan(f"view_{k:02d}", k, None, None) for k in range(len(inputs))]
    else:
        inp = first
        scan, cuts = _scan(inp, options)
        if options.split_at == "triggers":
            what = f"{inp.path}: topic {options.trigger_topic or inp.topic}"
            if options.trigger_topic not in (None, inp.topic):
                cuts = _trigger_cuts(inp.path, options.trigger_topic, options)
            kind = (f"{options.trigger_edge} trigger edges"
                    + (f" of channel {options.trigger_id}" if options.trigger_id is not None else ""))
            fix = "check the trigger cable and --trigger-id / --trigger-edge, or --split-at servo-start"
        else:
            what = f"{inp.path}: topic {options.servo_topic}"
            cuts = np.unique(np.array([s for s, w, _ in servo_msgs[0][0] if w == "START"], np.int64))
            kind = "servo START messages"
            fix = "name the servo topic with --servo-topic, or --split-at triggers"
        if cuts.size == 0:
            raise InputError(f"{what}: no {kind} found, so nothing to cut at; {fix}")
        if options.views is not None and cuts.size != options.views:
            raise InputError(f"{what}: found {cuts.size} {kind} but --views {options.views}; each view needs one "
                             f"cut: {fix} (or fix --views)")
        bounds, pre = _view_bounds(cuts, options.pre_roll_ns)
        edges = [None, *bounds.tolist(), None]
        plans = [_ViewPlan(f"view_{k:02d}", 0, edges[k], edges[k + 1], cut_ns=int(cuts[k]))
                 for k in range(cuts.size)]
        split = {"at": options.split_at, "cuts_ns": cuts.tolist(), "pre_roll_ns": pre,
                 "source_topic": ((options.trigger_topic or inp.topic) if options.split_at == "triggers"
                                  else options.servo_topic)}
        if options.split_at == "triggers":
            split.update(edge=options.trigger_edge, trigger_id=options.trigger_id)
        say(f"  {inp.path}: {cuts.size} {kind}: {cuts.size} views (pre-roll {pre / 1e6:g} ms)")

    # ----- poses
    n = len(plans)
    if options.poses is not None:
        poses, azimuths = _read_poses(options.poses, n)
        pose_source = f"file {options.poses}"
    elif options.ring is not None:
        poses = ring_poses(n, options.ring, options.ring_elevation_deg, (0.0, 0.0, 0.0), options.ring_offset_deg)
        azimuths = [options.ring_offset_deg + 360.0 * k / n for k in range(n)]
        pose_source = (f"ring: radius {options.ring:g} m, elevation {options.ring_elevation_deg:g} deg, "
                       f"first azimuth {options.ring_offset_deg:g} deg, looking at the origin")
    elif n == 1:
        poses, azimuths = [np.eye(4)], [None]
        pose_source = "unknown: identity (a single view)"
    else:
        raise InputError(f"import-bags: {n} views need poses: give --poses FILE (one per view) or --ring RADIUS")
    for plan, T, az in zip(plans, poses, azimuths):
        plan.T_world_cam, plan.azimuth_deg = np.asarray(T, np.float64), az

    # ----- write
    for text in notes:
        warnings.warn(text, SessionImportWarning, stacklevel=2)
    with atomic_output(out, overwrite=overwrite, directory=True) as tmp:
        tmp.mkdir()
        if split is None:
            for plan in plans:
                inp = inputs[plan.source]
                if inp.encoding != "array":
                    plan.encoding, plan.passed_through = inp.encoding, True
                    _write_passthrough(tmp, plan, inp, camera, options, servo_msgs[plan.source])
                else:
                    plan.encoding = _target_encoding(inp, _scan(inp)[0])
                    _write_reencoded(tmp, [plan], inp, camera, options, servo_msgs[plan.source])
                _check_view(plan, inp)
                say(f"  {plan.name}: {inp.path} ({inp.encoding}{', passed through' if plan.passed_through else ''}"
                    f"{'' if plan.passed_through else ' -> ' + plan.encoding}): {plan.stats.events} events")
        else:
            inp = first
            enc = _target_encoding(inp, scan)
            for plan in plans:
                plan.encoding = enc
            _write_reencoded(tmp, plans, inp, camera, options, servo_msgs[0])
            for plan in plans:
                _check_view(plan, inp)
                say(f"  {plan.name}: cut at {plan.cut_ns} ns: {plan.stats.events} events, "
                    f"{plan.stats.triggers} trigger edges")
        doc = _document(inputs, plans, intr, intr_kind, camera, width, height, pose_source, split, options,
                        servo_msgs, notes)
        write_session_yaml(tmp, doc)
    total = sum(p.stats.events for p in plans)
    return ImportResult(root=out, views=doc["views"], inputs=doc["source"]["inputs"], events=total,
                        seconds=time.perf_counter() - t_start, warnings=notes)


def _scan(inp: _Input, options: ImportOptions | None = None) -> tuple[_Stats, np.ndarray]:
    """A decoding pass over the input's event topic: counts, time range, time grid, and (given
    options with --split-at triggers on this topic) the cutting trigger edges."""
    from ..io.bag_reader import TopicDecoder, open_bag

    st = _Stats()
    cuts = []
    want = options is not None and options.split_at == "triggers" and options.trigger_topic in (None, inp.topic)
    with open_bag(inp.path) as bag:
        dec = TopicDecoder(bag, inp.topic)
        for ev, tr in _batches(bag, inp.topic, dec):
            st.add(ev, tr)
            if want:
                cuts.append(_edges(tr, options))
    return st, np.unique(np.concatenate(cuts)) if cuts else np.empty(0, np.int64)


def _check_view(plan: _ViewPlan, inp: _Input) -> None:
    if plan.stats.events == 0:
        where = "" if plan.lo is None and plan.hi is None else f" in [{plan.lo}, {plan.hi}) ns"
        raise InputError(f"{inp.path}: topic {inp.topic}: view {plan.name} has no events{where} (an empty "
                         "recording, or a cut with nothing after it); import a bag with events, or check the cuts")


def _document(inputs, plans, intr, intr_kind, camera, width, height, pose_source, split, options, servo_msgs,
              notes) -> dict:
    per_input = {}
    for plan in plans:
        per_input.setdefault(plan.source, []).append(plan)
    records = []
    for k, inp in enumerate(inputs):
        ps = per_input.get(k, [])
        firsts = [p.stats.first for p in ps if p.stats.first is not None]
        lasts = [p.stats.last for p in ps if p.stats.last is not None]
        records.append({
            "path": str(inp.path.resolve()), "topic": inp.topic, "msgtype": inp.msgtype, "encoding": inp.encoding,
            "storage": inp.storage, "width": inp.width, "height": inp.height, "messages": inp.messages,
            "events": sum(p.stats.events for p in ps), "trigger_events": sum(p.stats.triggers for p in ps),
            "first_ns": min(firsts) if firsts else None, "last_ns": max(lasts) if lasts else None,
            "bag_start_ns": inp.bag_start_ns, "bag_end_ns": inp.bag_end_ns,
            "camera_info_topic": inp.camera_info_topic,
            "views": [p.name for p in ps]})
    joints = [j[0][1][0] for _, j in servo_msgs if j]      # the first joint name of the first JointState
    views = []
    for plan in plans:
        st = plan.stats
        views.append(view_record(
            plan.name, "train", plan.T_world_cam, azimuth_deg=plan.azimuth_deg,
            events=st.events, trigger_events=st.triggers,
            imported={"input": plan.source, "encoding": plan.encoding, "passed_through": plan.passed_through,
                      "packets": plan.packets, "first_ns": st.first, "last_ns": st.last,
                      "range_ns": [plan.lo, plan.hi], "cut_ns": plan.cut_ns}))
    cam = camera_record(width, height, camera["K"], camera["D"], distortion_model=camera["distortion_model"])
    cam["intrinsics_source"] = intr_kind
    source = {"kind": "import", "inputs": records, "split": split, "calibration": intr["source"],
              "poses": pose_source, "notes": list(notes)}
    return session_document(
        source=source,
        rig={"kind": "imported", "ring_radius_m": options.ring,
             "elevation_deg": options.ring_elevation_deg if options.ring is not None else None,
             "look_at": [0.0, 0.0, 0.0] if options.ring is not None else None,
             "firmware_version": None, "device_serial": None},
        camera=cam,
        servo=servo_record(joints[0]) if joints else None,
        thresholds={"c_pos": float(options.c_pos), "c_neg": float(options.c_neg), "eps": None,
                    "source": "import options (--c-pos / --c-neg; default the paper's "
                              f"{DEFAULT_THRESHOLD:g}): the bags carry no bias settings"},
        views=views)
