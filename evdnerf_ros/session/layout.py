"""The capture-session layout (DESIGN.md), read and written in one place.

```
<session>/session.yaml    format, camera, thresholds, rig, per-view records (below)
<session>/<view>/         one rosbag2 per view (the record's `bag`, relative to the session)
```
A view record: `name`, `bag`, `split` (train | val), `azimuth_deg`, `T_world_cam` (4x4,
OpenCV axes, metres), optional `frames` (blurred frames .npz), optional `ground_truth`
(simulation only: `clock_offset_ns`, `device_offset_ns`, `file`), and `sync` once
`evdnerf sync` has run: `offset_ns` (the view clock's reading at the common time origin, so
that `t_common = t_view - offset_ns`), `method`, `confidence` and per-method estimates.

session.yaml is rewritten atomically; bags are never modified.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from ..atomic import atomic_output
from ..errors import InputError

SESSION_FORMAT = "evdnerf-rig-session"
SESSION_FORMAT_VERSION = 1
SPLITS = ("train", "val")


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


DEFAULT_EVENTS_TOPIC = "/event_camera/events"
DEFAULT_TRIGGER_TOPIC = "/rig/servo/trigger"


def session_topics(session: "Session", events_topic: str | None = None,
                   trigger_topic: str | None = None) -> tuple[str, str]:
    """(events topic, servo START/DONE topic): given ones, else session.yaml's, else defaults."""
    cam = session.data.get("camera") or {}
    ev = events_topic or (cam.get("topics") or {}).get("events") or DEFAULT_EVENTS_TOPIC
    servo = session.data.get("servo") or {}
    tr = trigger_topic or servo.get("trigger") or DEFAULT_TRIGGER_TOPIC
    return str(ev), str(tr)


def session_yaml_path(root) -> Path:
    return Path(root) / "session.yaml"


def write_session_yaml(root, data: dict, *, overwrite: bool = False) -> Path:
    """Write (or atomically replace, with overwrite=True) `<root>/session.yaml`."""
    path = session_yaml_path(root)
    with atomic_output(path, overwrite=overwrite) as tmp:
        tmp.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def load_session(root) -> Session:
    """Read and validate a session folder; every error names the file and the view."""
    root = Path(root)
    path = session_yaml_path(root)
    if not path.is_file():
        raise InputError(f"{root}: no session.yaml; a session folder is what `evdnerf simulate` "
                         "or the capture node writes")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != SESSION_FORMAT:
        raise InputError(f"{path}: not a session file (format must be {SESSION_FORMAT!r})")
    if data.get("format_version") != SESSION_FORMAT_VERSION:
        raise InputError(f"{path}: format_version {data.get('format_version')!r} is not supported "
                         f"(this toolkit reads version {SESSION_FORMAT_VERSION})")
    cam = _section(data, "camera", path)
    width, height = _int(cam, "width", path, "camera"), _int(cam, "height", path, "camera")
    K = _matrix(cam.get("K"), (3, 3), path, "camera.K")
    D = np.asarray(cam.get("D", [0.0] * 5), np.float64)
    th = _section(data, "thresholds", path)
    c_pos, c_neg = float(th.get("c_pos", np.nan)), float(th.get("c_neg", np.nan))
    if not (np.isfinite(c_pos) and np.isfinite(c_neg) and c_pos > 0 and c_neg > 0):
        raise InputError(f"{path}: thresholds.c_pos / c_neg must be finite and > 0")
    raw_views = data.get("views")
    if not isinstance(raw_views, list) or not raw_views:
        raise InputError(f"{path}: `views` must be a non-empty list")
    views, seen = [], set()
    for i, v in enumerate(raw_views):
        where = f"views[{i}]"
        if not isinstance(v, dict) or not isinstance(v.get("name"), str) or not v["name"]:
            raise InputError(f"{path}: {where} needs a `name`")
        name = v["name"]
        if name in seen:
            raise InputError(f"{path}: duplicate view name {name!r}; view names must be unique")
        seen.add(name)
        split = v.get("split", "train")
        if split not in SPLITS:
            raise InputError(f"{path}: view {name}: split {split!r} is not one of {SPLITS}")
        bag = root / str(v.get("bag", name))
        T = _matrix(v.get("T_world_cam"), (4, 4), path, f"view {name}: T_world_cam")
        _check_rigid(T, path, name)
        frames = v.get("frames")
        views.append(ViewRecord(name=name, bag=bag, split=split,
                                azimuth_deg=None if v.get("azimuth_deg") is None else float(v["azimuth_deg"]),
                                T_world_cam=T, frames=None if frames is None else root / frames,
                                ground_truth=v.get("ground_truth"), sync=v.get("sync")))
    return Session(root=root, width=width, height=height, K=K, D=D, c_pos=c_pos, c_neg=c_neg,
                   eps=None if th.get("eps") is None else float(th["eps"]), views=views,
                   servo=data.get("servo"), time=data.get("time") or {}, data=data)


def _section(data, key, path) -> dict:
    sec = data.get(key)
    if not isinstance(sec, dict):
        raise InputError(f"{path}: missing section `{key}`")
    return sec


def _int(sec, key, path, where) -> int:
    v = sec.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
        raise InputError(f"{path}: {where}.{key} must be a positive integer, got {v!r}")
    return v


def _matrix(value, shape, path, where) -> np.ndarray:
    try:
        m = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != shape:
        raise InputError(f"{path}: {where} must be a {shape[0]}x{shape[1]} matrix")
    if not np.all(np.isfinite(m)):
        raise InputError(f"{path}: {where} contains NaN or inf")
    return m


def _check_rigid(T, path, name) -> None:
    R = T[:3, :3]
    if (np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6
            or np.abs(T[3] - [0, 0, 0, 1]).max() > 0):
        raise InputError(f"{path}: view {name}: T_world_cam is not a rigid transform "
                         "(rotation must be orthonormal with det +1, last row 0 0 0 1)")
