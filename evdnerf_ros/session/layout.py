"""The capture-session layout (DESIGN.md): the reader and the schema of session.yaml.

```
<session>/session.yaml    format, camera, thresholds, rig, per-view records (below)
<session>/<view>/         one rosbag2 per view (the record's `bag`, relative to the session)
```
A view record: `name`, `bag`, `split` (train | val), `azimuth_deg`, `T_world_cam` (4x4,
OpenCV axes, metres), optional `frames` (blurred frames .npz), optional `ground_truth`
(simulation only: `clock_offset_ns`, `device_offset_ns`, `file`), and `sync` once
`evdnerf sync` has run: `offset_ns` (the view clock's reading at the common time origin, so
that `t_common = t_view - offset_ns`), `method`, `confidence` and per-method estimates.

A moving view also has `moving_arc_deg` (the azimuth its camera sweeps; None for a static
view) and its pose topic carries the trajectory.

A captured view may record its own contrast thresholds: `thresholds` (`c_pos`, `c_neg`, as the
session's) with `thresholds_source` (`bias model`: the camera driver's bias -> threshold model
for the view's biases; `options`: given), the camera's `biases` in force when it began
({name: integer}) and `bias_changes` (each: `sensor_ns` or null, `values` {name: integer},
optional `thresholds` after it). The session's `thresholds` stay the one pair training uses.

The one writer of this layout is :mod:`evdnerf_ros.session.recorder` (per-view bags and
session.yaml); it checks every session.yaml it writes with :func:`check_session`, the same
schema :func:`load_session` applies, so a document the reader would refuse is never written.
session.yaml is rewritten atomically; bags are never modified. Topic names:
:mod:`evdnerf_ros.topics`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.poses import check_rigid
from ..yamlcheck import Where, choice, is_number, load_yaml, mapping, matrix, number, number_in, sequence, text_in, \
    type_name
from ..io.trainingset import C_MAX, T_LIMIT
from ..topics import EVENTS, SERVO_TRIGGER

SESSION_FORMAT = "evdnerf-rig-session"
SESSION_FORMAT_VERSION = 1
SPLITS = ("train", "val")
#: a view's `thresholds_source`
THRESHOLD_SOURCES = ("bias model", "options")
#: bias values are the drivers' register fields or offsets (EVK4); any int32 passes the layout
BIAS_LIMIT = 2**31


@dataclass
class ViewRecord:
    name: str
    bag: Path                      # absolute path of the view's rosbag2
    split: str
    azimuth_deg: float | None
    T_world_cam: np.ndarray        # (4, 4) float64
    frames: Path | None = None
    ground_truth: dict | None = None
    sync: dict | None = None
    thresholds: tuple[float, float] | None = None   # the view's own (c_pos, c_neg), when recorded


@dataclass
class Session:
    root: Path
    width: int
    height: int
    K: np.ndarray                  # (3, 3)
    D: np.ndarray
    c_pos: float
    c_neg: float
    eps: float | None
    views: list[ViewRecord]
    servo: dict | None = None
    time: dict = field(default_factory=dict)
    data: dict = field(default_factory=dict)   # the whole parsed session.yaml

    def view(self, name: str) -> ViewRecord:
        for v in self.views:
            if v.name == name:
                return v
        raise InputError(f"{self.root}: no view {name!r}; views: {', '.join(v.name for v in self.views)}")


def session_topics(session: "Session", events_topic: str | None = None,
                   trigger_topic: str | None = None) -> tuple[str, str]:
    """(events topic, servo START/DONE topic): given ones, else session.yaml's, else defaults."""
    cam = session.data.get("camera") or {}
    ev = events_topic or (cam.get("topics") or {}).get("events") or EVENTS
    servo = session.data.get("servo") or {}
    tr = trigger_topic or servo.get("trigger") or SERVO_TRIGGER
    return str(ev), str(tr)


def session_yaml_path(root) -> Path:
    return Path(root) / "session.yaml"


def load_session(root) -> Session:
    """Read and validate a session folder; every error names the file and the key at fault
    (``session.yaml: views[3].T_world_cam``) and says what is expected."""
    root = Path(root)
    path = session_yaml_path(root)
    if not root.is_dir():
        raise InputError(f"{root}: no such session folder")
    if not path.is_file():
        raise InputError(f"{root}: no session.yaml; a session folder is what `evdnerf simulate` "
                         "or the capture node writes")
    data = load_yaml(path, what="session.yaml")
    session = _check_session(root, path, data)
    unfinished = [v.get("name") for v in data["views"] if isinstance(v, dict) and v.get("complete") is False]
    if unfinished:
        raise InputError(f"{path}: views {unfinished} are incomplete (the capture was interrupted or failed "
                         "in them); record them again with `evdnerf capture -o SESSION --resume`")
    return session


def check_session(root, data, *, path=None) -> Session:
    """Validate a parsed session.yaml document `data` of the session folder `root` with the
    reader's schema (the check :func:`load_session` applies); errors name `path` (default
    ``<root>/session.yaml``) and the key at fault. Returns the Session it describes."""
    root = Path(root)
    return _check_session(root, Path(path) if path is not None else session_yaml_path(root), data)


# =========================================================================== schema
#
# One check of everything the toolkit reads from session.yaml: types, ranges (check_number),
# required keys. Other keys are kept as they are (they are the session's own record).

# Contrast thresholds outside (0, C_MAX] and times beyond +-T_LIMIT ns are refused, as in a
# training set. Sensor size limit (pixel coordinates are uint16 everywhere).
SIZE_MAX = 65535


def _servo_track(track, where: Where) -> None:
    """``{scene_ns: [...], deg: [...]}``: equal, non-empty lists, times increasing (the servo angles
    the virtual rig's camera twin rendered over a view)."""
    mapping(track, where, allowed=("scene_ns", "deg"), required=("scene_ns", "deg"))
    times = sequence(track["scene_ns"], where / "scene_ns", min_len=1)
    angles = sequence(track["deg"], where / "deg")
    if len(angles) != len(times):
        (where / "deg").fail(f"holds {len(angles)} angle{'s' * (len(angles) != 1)} for the {len(times)} "
                             "times of scene_ns")
    t = [number(v, where / "scene_ns" / i, integer=True, low=-T_LIMIT, high=T_LIMIT) for i, v in enumerate(times)]
    for i, v in enumerate(angles):
        number(v, where / "deg" / i, low=-360, high=360)
    if any(b <= a for a, b in zip(t, t[1:])):
        where.fail("scene_ns must increase")


def _int_ns(sec: dict, key: str, where: Where, *, required: bool = False):
    return number_in(sec, key, where, required=required, integer=True, low=-T_LIMIT, high=T_LIMIT)


def _check_joint(servo: dict, where: Where) -> None:
    """The servo's joint, where the rig knows it (``sim.joint.joint_record``): axis and pivot
    (world) and the angle every ``step_ns`` after the servo's start; all three or none."""
    keys = [k for k in ("axis", "pivot", "angle_rad") if servo.get(k) is not None]
    if not keys:
        return
    if len(keys) != 3:
        (where / keys[0]).fail("comes with axis, pivot and angle_rad together (the joint the rig knows), or none")
    axis = matrix([servo["axis"]], (1, 3), where / "axis")
    if not np.linalg.norm(axis) > 0:
        (where / "axis").fail("must be a non-zero direction")
    matrix([servo["pivot"]], (1, 3), where / "pivot")
    angle = mapping(servo["angle_rad"], where / "angle_rad")
    number_in(angle, "step_ns", where / "angle_rad", required=True, integer=True, low=1, high=T_LIMIT)
    values = sequence(angle.get("values"), where / "angle_rad" / "values", min_len=2)
    matrix([values], (1, len(values)), where / "angle_rad" / "values", max_abs=1e3)


def _check_session(root: Path, path: Path, data) -> Session:
    top = Where(path)
    if not isinstance(data, dict) or data.get("format") != SESSION_FORMAT:
        raise InputError(f"{path}: not a session file (format must be {SESSION_FORMAT!r})")
    if data.get("format_version") != SESSION_FORMAT_VERSION or isinstance(data.get("format_version"), bool):
        raise InputError(f"{path}: format_version {data.get('format_version')!r} is not supported "
                         f"(this toolkit reads version {SESSION_FORMAT_VERSION})")
    w = top / "camera"
    cam = mapping(data.get("camera"), w)
    width = number_in(cam, "width", w, integer=True, low=1, high=SIZE_MAX)
    height = number_in(cam, "height", w, integer=True, low=1, high=SIZE_MAX)
    K = matrix(cam.get("K"), (3, 3), w / "K")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise (w / "K").error(f"is not a pinhole intrinsic matrix (need fx, fy > 0 and last row [0, 0, 1]); "
                              f"got {K.tolist()}")
    D = cam.get("D", [0.0] * 5)
    if not isinstance(D, list) or len(D) > 14 or not all(is_number(v) for v in D) \
            or not np.all(np.isfinite(np.asarray(D, np.float64))):
        raise (w / "D").error("must be a list of at most 14 finite numbers (distortion coefficients)")
    D = np.asarray(D, np.float64)
    if cam.get("topics") is not None:
        tw = w / "topics"
        topics = mapping(cam["topics"], tw)
        for k in topics:
            _topic(topics, k, tw)
    w = top / "thresholds"
    th = mapping(data.get("thresholds"), w)
    c_pos, c_neg = _threshold_pair(th, w)
    eps = number_in(th, "eps", w, required=False, low=0, low_open=True, high=1.0)
    time_sec = mapping(data.get("time"), top / "time", optional=True) or {}
    for k in ("scene_start_ns", "scene_end_ns", "motion_start_ns", "motion_end_ns"):
        _int_ns(time_sec, k, top / "time")
    ms, me = time_sec.get("motion_start_ns"), time_sec.get("motion_end_ns")
    if ms is not None and me is not None and me <= ms:
        raise (top / "time" / "motion_end_ns").error(f"{me} must be after motion_start_ns {ms}")
    servo = mapping(data.get("servo"), top / "servo", optional=True)
    if servo is not None:
        for k in ("trigger", "joint_states"):
            _topic(servo, k, top / "servo")
        _int_ns(servo, "start_ns_scene", top / "servo")
        _check_joint(servo, top / "servo")
    if data.get("scene_bounds") is not None:
        b = matrix(data["scene_bounds"], (2, 3), top / "scene_bounds")
        if np.any(b[1] < b[0]):
            raise (top / "scene_bounds").error("must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max >= min")
    raw_views = data.get("views")
    if not isinstance(raw_views, list) or not raw_views:
        raise (top / "views").error("must be a non-empty list of view records")
    views, seen = [], set()
    for i, v in enumerate(raw_views):
        views.append(_check_view(root, v, top / "views" / i, seen))
    return Session(root=root, width=width, height=height, K=K, D=D, c_pos=c_pos, c_neg=c_neg,
                   eps=None if eps is None else float(eps), views=views, servo=servo, time=time_sec, data=data)


def _threshold_pair(th: dict, where: Where) -> tuple[float, float]:
    return (float(number_in(th, "c_pos", where, low=0, low_open=True, high=C_MAX)),
            float(number_in(th, "c_neg", where, low=0, low_open=True, high=C_MAX)))


def _bias_values(value, where: Where) -> dict:
    values = mapping(value, where)
    for name, v in values.items():
        if isinstance(v, bool):
            (where / str(name)).fail(f"expected an integer bias value, got {v!r}")
        number(v, where / str(name), integer=True, low=-BIAS_LIMIT, high=BIAS_LIMIT)
    return values


def _view_biases(v: dict, where: Where) -> tuple[float, float] | None:
    """A captured view's thresholds, biases and bias changes (module doc); its (c_pos, c_neg)."""
    th = mapping(v.get("thresholds"), where / "thresholds", optional=True)
    pair = None if th is None else _threshold_pair(th, where / "thresholds")
    if v.get("thresholds_source") is not None:
        choice(v["thresholds_source"], where / "thresholds_source", THRESHOLD_SOURCES)
    if v.get("biases") is not None:
        _bias_values(v["biases"], where / "biases")
    if v.get("bias_changes") is not None:
        for i, c in enumerate(sequence(v["bias_changes"], where / "bias_changes")):
            cw = where / "bias_changes" / i
            mapping(c, cw, required=("values",))
            _int_ns(c, "sensor_ns", cw)
            _bias_values(c["values"], cw / "values")
            if c.get("thresholds") is not None:
                _threshold_pair(mapping(c["thresholds"], cw / "thresholds"), cw / "thresholds")
    return pair


def _topic(sec: dict, key: str, where: Where) -> None:
    value = sec.get(key)
    if value is not None and (not isinstance(value, str) or not value.startswith("/")):
        raise (where / key).error(f"must be an absolute topic name such as '/event_camera/events', got {value!r}")


def _check_view(root: Path, v, where: Where, seen: set) -> ViewRecord:
    if not isinstance(v, dict):
        raise where.error(f"must be a mapping with name, bag, split, T_world_cam; got a {type_name(v)}")
    name = v.get("name")
    if not isinstance(name, str) or not name or "/" in name or name in (".", ".."):
        raise (where / "name").error(f"needs a `name`: a non-empty string without '/', got {name!r}")
    if name in seen:
        raise (where / "name").error(f"duplicate view name {name!r}; view names must be unique")
    seen.add(name)
    split = v.get("split", "train")
    if split not in SPLITS:
        raise (where / "split").error(f"view {name}: split {split!r} is not one of {SPLITS}")
    bag = text_in(v, "bag", where, default=name)
    T = matrix(v.get("T_world_cam"), (4, 4), where / "T_world_cam")
    try:
        check_rigid(T, f"view {name}: T_world_cam")
    except InputError as exc:
        raise (where / "T_world_cam").error(str(exc)) from None
    azimuth = number_in(v, "azimuth_deg", where, required=False, low=-1e6, high=1e6)
    frames = text_in(v, "frames", where)
    gt = mapping(v.get("ground_truth"), where / "ground_truth", optional=True)
    if gt is not None:
        for k in ("clock_offset_ns", "device_offset_ns", "sensor_zero_scene_ns"):
            _int_ns(gt, k, where / "ground_truth")
        # chunks the virtual rig's camera twin rendered with stale joint angles (rig.camera.virtual)
        number_in(gt, "stale_renders", where / "ground_truth", required=False, integer=True, low=0, high=1e12)
        if gt.get("servo_track") is not None:
            _servo_track(gt["servo_track"], where / "ground_truth" / "servo_track")
    sync = mapping(v.get("sync"), where / "sync", optional=True)
    if sync is not None:
        _int_ns(sync, "offset_ns", where / "sync")
    thresholds = _view_biases(v, where)
    return ViewRecord(name=name, bag=root / bag, split=split,
                      azimuth_deg=None if azimuth is None else float(azimuth), T_world_cam=T,
                      frames=None if frames is None else root / frames, ground_truth=gt, sync=sync,
                      thresholds=thresholds)
