"""Timestamped robot poses from a bag (nav_msgs/Odometry, geometry_msgs/PoseStamped,
tf2_msgs/TFMessage), a YAML file or a CSV file -> (t_ns int64 (N,), T_world_robot (N, 4, 4)).

YAML::

    frame_id: world            # optional, informative
    poses:
      - {t: 0.0, position: [0, 0, 1], orientation: [0, 0, 0, 1]}   # t in s, or t_ns: int
      ...

orientation is a quaternion (x, y, z, w) as in ROS messages.
CSV: a header row naming ``t_ns`` (or ``t`` in seconds), ``x, y, z, qx, qy, qz, qw``.

Bags: the pose topic is ``topic`` or, when not given, the only topic of one of the three
types. Stamps come from the message header (the bag time when the header stamp is 0).
From ``/tf`` the transforms whose ``child_frame_id`` is ``child_frame`` are used (one
direct parent -> child transform; chains are not composed).

Every loader checks what interpolation needs and names the file and the pose at fault:
finite values, unit quaternions, strictly increasing times.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import yaml

from ..errors import InputError
from .guard import read_text
from ..geometry.poses import check_increasing_times, check_rigid
from ..geometry.rotations import quat_from_ros, quat_to_matrix
from .messages import stamp_to_ns

POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped", "tf2_msgs/msg/TFMessage")
QUAT_TOL = 1e-3


def _pose(src: str, i: int, position, orientation) -> np.ndarray:
    try:
        p = np.asarray(position, dtype=np.float64).reshape(3)
        q = np.asarray(orientation, dtype=np.float64).reshape(4)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{src}: pose {i}: position needs 3 numbers and orientation 4 (x, y, z, w)") from None
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise InputError(f"{src}: pose {i} has NaN or infinite values (position {p.tolist()}, "
                         f"orientation {q.tolist()}); remove or repair that pose")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > QUAT_TOL:
        raise InputError(f"{src}: pose {i}: quaternion {q.tolist()} has norm {n:.6g}, not 1; write orientation "
                         "as a unit quaternion (x, y, z, w)")
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(quat_from_ros(q / n))
    T[:3, 3] = p
    return T


def check_times(src: str, t: np.ndarray) -> np.ndarray:
    return check_increasing_times(t, src, min_count=2)


#: Pose times (ns) beyond +-T_LIMIT are refused (int64 arithmetic on them must not overflow).
T_LIMIT = 2**62


def _seconds_to_ns(src, i, value) -> int:
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{src}: pose {i}: time {value!r} is not a number") from None
    if not np.isfinite(v):
        raise InputError(f"{src}: pose {i}: time is {value!r}; every pose needs a finite time")
    if abs(v) * 1e9 > T_LIMIT:
        raise InputError(f"{src}: pose {i}: time {value!r} s is beyond +-{T_LIMIT / 1e9:.3g} s")
    return int(round(v * 1e9))


def _ns(src, i, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(f"{src}: pose {i}: t_ns must be an integer number of nanoseconds, got {value!r}")
    if abs(value) > T_LIMIT:
        raise InputError(f"{src}: pose {i}: t_ns {value} is beyond +-2**62 ns")
    return value


def load_yaml_poses(path) -> tuple[np.ndarray, np.ndarray]:
    path = Path(path)
    src = str(path)
    text = read_text(path, what="trajectory file")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(f"{src}: not valid YAML ({' '.join(str(exc).split())})") from None
    except (RecursionError, ValueError, OverflowError) as exc:
        raise InputError(f"{src}: not a usable YAML document ({type(exc).__name__})") from None
    poses = data.get("poses") if isinstance(data, dict) else None
    if not isinstance(poses, list):
        raise InputError(f"{src}: expected a mapping with a 'poses' list of {{t, position, orientation}}")
    ts, Ts = [], []
    for i, p in enumerate(poses):
        if not isinstance(p, dict) or "position" not in p or "orientation" not in p or not ({"t", "t_ns"} & set(p)):
            raise InputError(f"{src}: pose {i} needs t (s) or t_ns, position [x, y, z] and orientation [x, y, z, w]")
        if "t_ns" in p:
            ts.append(_ns(src, i, p["t_ns"]))
        else:
            ts.append(_seconds_to_ns(src, i, p["t"]))
        Ts.append(_pose(src, i, p["position"], p["orientation"]))
    return check_times(src, np.array(ts, np.int64)), np.array(Ts)


def load_csv_poses(path) -> tuple[np.ndarray, np.ndarray]:
    path = Path(path)
    src = str(path)
    text = read_text(path, what="trajectory file")
    try:
        rows = list(csv.DictReader(io.StringIO(text, newline="")))
    except csv.Error as exc:
        raise InputError(f"{src}: not a readable CSV file ({exc})") from None
    if not rows:
        raise InputError(f"{src}: no rows; expected a header t_ns (or t),x,y,z,qx,qy,qz,qw and one row per pose")
    cols = set(rows[0])
    need = {"x", "y", "z", "qx", "qy", "qz", "qw"}
    if not need <= cols or not ({"t", "t_ns"} & cols):
        raise InputError(f"{src}: header has {sorted(cols)}; need t_ns (or t in seconds) and {sorted(need)}")
    ts, Ts = [], []
    for i, r in enumerate(rows):
        try:
            if "t_ns" in cols:
                ts.append(_ns(src, i, int(r["t_ns"])))
            else:
                ts.append(_seconds_to_ns(src, i, r["t"]))
            vals = [float(r[k]) for k in ("x", "y", "z", "qx", "qy", "qz", "qw")]
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"{src}: line {i + 2}: not a number in {r}") from None
        Ts.append(_pose(f"{src}: line {i + 2}", i, vals[:3], vals[3:]))
    return check_times(src, np.array(ts, np.int64)), np.array(Ts)


def load_bag_poses(path, topic: str | None = None, *, child_frame: str = "base_link"):
    from .rosbag2 import open_bag

    src = str(path)
    with open_bag(path) as bag:
        topics = bag.topics
        if topic is None:
            cands = [n for n, s in topics.items() if s.msgtype in POSE_TYPES]
            if len(cands) != 1:
                listing = ", ".join(f"{n} [{s.msgtype}]" for n, s in topics.items()) or "none"
                raise InputError(f"{src}: {'several' if cands else 'no'} pose topics ({listing}); choose one with "
                                 f"trajectory_topic (types: {', '.join(POSE_TYPES)})")
            topic = cands[0]
        msgtype = bag.topic(topic).msgtype
        if msgtype not in POSE_TYPES:
            raise InputError(f"{src}: topic {topic} carries {msgtype}; a trajectory needs one of {list(POSE_TYPES)}")
        ts, Ts = [], []
        where = f"{src}: topic {topic}"
        for i, m in enumerate(bag.messages(topic)):
            msg = bag.deserialize(m.data, msgtype)
            if msgtype == "tf2_msgs/msg/TFMessage":
                for tf in msg.transforms:
                    if tf.child_frame_id != child_frame:
                        continue
                    tr, q = tf.transform.translation, tf.transform.rotation
                    Ts.append(_pose(where, len(ts), [tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w]))
                    ts.append(stamp_to_ns(tf.header.stamp) or m.t_ns)
                continue
            pose = msg.pose.pose if msgtype == "nav_msgs/msg/Odometry" else msg.pose
            o, p = pose.orientation, pose.position
            Ts.append(_pose(where, i, [p.x, p.y, p.z], [o.x, o.y, o.z, o.w]))
            ts.append(stamp_to_ns(msg.header.stamp) or m.t_ns)
    if msgtype == "tf2_msgs/msg/TFMessage" and not ts:
        raise InputError(f"{src}: topic {topic} has no transform with child_frame_id {child_frame!r}; "
                         "set trajectory_child_frame to the robot's frame")
    return check_times(f"{src}: topic {topic}", np.array(ts, np.int64)), np.array(Ts)


def load_poses(path, *, topic: str | None = None, child_frame: str = "base_link"):
    """(t_ns, T_world_robot) from a bag, .yaml/.yml or .csv (see the module doc)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such trajectory file or bag")
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml") and path.is_file():
        return load_yaml_poses(path)
    if suffix == ".csv":
        return load_csv_poses(path)
    return load_bag_poses(path, topic, child_frame=child_frame)


def extrinsics(xyz, rpy_deg=None, quat_xyzw=None, *, what: str = "camera extrinsics") -> np.ndarray:
    """T_robot_cam from a translation and either roll/pitch/yaw (deg, fixed axes x, y, z) or a quaternion.
    Non-finite values, a non-unit quaternion or a non-rigid result raise InputError."""
    p = np.asarray(xyz, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"{what}: translation must be 3 finite numbers, got {list(np.ravel(xyz))}")
    T = np.eye(4)
    T[:3, 3] = p
    if quat_xyzw is not None and len(quat_xyzw):
        T[:3, :3] = _pose(what, 0, p, quat_xyzw)[:3, :3]
    elif rpy_deg is not None:
        r = np.radians(np.asarray(rpy_deg, dtype=np.float64))
        if r.shape != (3,) or not np.all(np.isfinite(r)):
            raise InputError(f"{what}: rpy must be 3 finite angles in degrees, got {list(np.ravel(rpy_deg))}")
        cr, sr, cp, sp, cy, sy = np.cos(r[0]), np.sin(r[0]), np.cos(r[1]), np.sin(r[1]), np.cos(r[2]), np.sin(r[2])
        Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        T[:3, :3] = Rz @ Ry @ Rx
    return check_rigid(T, what)


def matrix_extrinsics(values, *, what: str = "camera extrinsics") -> np.ndarray:
    """T_robot_cam from 16 row-major numbers; InputError unless rigid."""
    return check_rigid(np.asarray(values, dtype=np.float64).reshape(4, 4) if np.size(values) == 16 else values,
                       what)

