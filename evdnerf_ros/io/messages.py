"""Build and read the standard ROS 2 messages the toolkit records (rosbags message objects).

Every builder validates its input and raises InputError naming the offending argument;
every time is int64 nanoseconds, converted exactly (integer arithmetic, no floats) to and
from ``builtin_interfaces/Time`` (``sec`` int32, ``nanosec`` uint32, ``nanosec`` < 1e9,
floor convention for negative times: -1 ns = sec -1, nanosec 999_999_999).

Message objects come from :func:`evdnerf_ros.io.typestore.ros2_typestore`; serialise them
with ``ros2_typestore().serialize_cdr(msg, msg.__msgtype__)`` or write them with
:meth:`evdnerf_ros.io.rosbag2.BagWriter.write`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import FormatError, InputError
from ..geometry.poses import check_rigid
from ..geometry.rotations import matrix_to_quat, quat_from_ros, quat_to_matrix, quat_to_ros
from .typestore import ros2_typestore

NS_PER_S = 1_000_000_000
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
UINT32_MAX = 2**32 - 1
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1

#: Number of distortion coefficients each known ROS distortion model takes.
DISTORTION_SIZES = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}

#: Largest | |q| - 1 | accepted (and then normalised) when reading a quaternion.
QUAT_NORM_TOL = 1e-3


def _types():
    return ros2_typestore().types


# --------------------------------------------------------------------------- time stamps


def _as_int(value, what: str) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise InputError(f"{what}: expected an integer number of nanoseconds, got a bool")
    if isinstance(value, (int, np.integer)):
        return int(value)
    raise InputError(f"{what}: expected an integer number of nanoseconds (int64), got "
                     f"{type(value).__name__} {value!r}; floats lose precision, convert with "
                     "int(round(seconds * 1e9)) only at the boundary")


def ns_to_sec_nanosec(ns, *, what: str = "time", ros1: bool = False) -> tuple[int, int]:
    """Split int64 ns into (sec, nanosec) with 0 <= nanosec < 1e9 (exact, floor convention).

    ROS 2 ``sec`` is int32; ROS 1 ``secs`` is uint32 (no negative times). Out of range
    raises InputError instead of wrapping.
    """
    ns = _as_int(ns, what)
    if not INT64_MIN <= ns <= INT64_MAX:
        raise InputError(f"{what}: {ns} ns does not fit int64")
    sec, nanosec = divmod(ns, NS_PER_S)
    lo, hi = (0, UINT32_MAX) if ros1 else (INT32_MIN, INT32_MAX)
    if not lo <= sec <= hi:
        kind = "ROS 1 time (uint32 seconds)" if ros1 else "builtin_interfaces/Time (int32 seconds)"
        raise InputError(f"{what}: {ns} ns is outside the range of a {kind}: seconds must lie in "
                         f"[{lo}, {hi}]; shift the time origin")
    return sec, nanosec


def ns_to_stamp(ns, *, what: str = "stamp"):
    """int64 ns -> ``builtin_interfaces/msg/Time`` message (exact)."""
    sec, nanosec = ns_to_sec_nanosec(ns, what=what)
    return _types()["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def stamp_to_ns(stamp, *, what: str = "stamp") -> int:
    """``builtin_interfaces/Time`` (anything with .sec/.nanosec, or a (sec, nanosec) pair) -> int ns.

    Exact integer arithmetic. A non-normalised nanosec (>= 1e9) is carried into the
    seconds exactly as ROS does; a result outside int64 raises InputError.
    """
    if isinstance(stamp, tuple):
        sec, nanosec = stamp
    else:
        try:
            sec, nanosec = stamp.sec, stamp.nanosec
        except AttributeError:
            raise InputError(f"{what}: expected a builtin_interfaces/Time or (sec, nanosec), got "
                             f"{type(stamp).__name__}") from None
    sec, nanosec = int(sec), int(nanosec)
    if nanosec < 0:
        raise InputError(f"{what}: nanosec {nanosec} is negative")
    ns = sec * NS_PER_S + nanosec
    if not INT64_MIN <= ns <= INT64_MAX:
        raise InputError(f"{what}: sec={sec}, nanosec={nanosec} does not fit int64 nanoseconds")
    return ns


def header(stamp_ns, frame_id: str = ""):
    """``std_msgs/msg/Header`` (ROS 2: stamp + frame_id)."""
    if not isinstance(frame_id, str):
        raise InputError(f"frame_id: expected a string, got {type(frame_id).__name__}")
    return _types()["std_msgs/msg/Header"](stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)


def header_stamp_ns(msg) -> int:
    """int ns of ``msg.header.stamp``."""
    return stamp_to_ns(msg.header.stamp, what=f"{getattr(msg, '__msgtype__', 'message')}.header.stamp")


# --------------------------------------------------------------------------- helpers


def _matrix(value, shape, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: not a numeric array ({exc})") from None
    if arr.shape != shape:
        raise InputError(f"{what}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what}: contains NaN or infinite values")
    return arr


def _vector(value, what: str, *, size: int | None = None) -> np.ndarray:
    if value is None:
        value = ()
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: not a numeric vector ({exc})") from None
    if arr.ndim != 1:
        raise InputError(f"{what}: expected a 1-D vector, got shape {arr.shape}")
    if size is not None and arr.size != size:
        raise InputError(f"{what}: expected {size} values, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what}: contains NaN or infinite values")
    return np.ascontiguousarray(arr)


def _dim(value, what: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{what}: expected a positive integer, got {value!r}")
    if not 0 < int(value) <= UINT32_MAX:
        raise InputError(f"{what}: {value} is not a positive uint32")
    return int(value)


# --------------------------------------------------------------------------- CameraInfo


def camera_info(width: int, height: int, K, D=(0.0, 0.0, 0.0, 0.0, 0.0), *, frame_id: str = "event_camera",
                stamp_ns: int = 0, distortion_model: str = "plumb_bob", R=None, P=None,
                binning_x: int = 0, binning_y: int = 0):
    """``sensor_msgs/msg/CameraInfo`` for a pinhole camera.

    K: 3x3 intrinsics (fx, fy > 0, K[2] = [0, 0, 1]); D: distortion coefficients (5 for
    plumb_bob, 8 for rational_polynomial, 4 for equidistant); R: rectification (identity by
    default); P: 3x4 projection (default ``[K | 0]``). ROI is left empty (full image).
    """
    width, height = _dim(width, "camera_info width"), _dim(height, "camera_info height")
    K = _matrix(K, (3, 3), "camera_info K")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.array_equal(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise InputError(f"camera_info K: not a pinhole intrinsic matrix "
                         f"(need fx, fy > 0, K[1,0] = 0 and last row [0, 0, 1]); got {K.tolist()}")
    if not isinstance(distortion_model, str) or not distortion_model:
        raise InputError("camera_info distortion_model: expected a non-empty string such as 'plumb_bob'")
    D = _vector(D, "camera_info D")
    need = DISTORTION_SIZES.get(distortion_model)
    if need is not None and D.size != need:
        raise InputError(f"camera_info D: distortion model {distortion_model!r} takes {need} "
                         f"coefficients, got {D.size}")
    R = np.eye(3) if R is None else _matrix(R, (3, 3), "camera_info R")
    if P is None:
        P = np.hstack([K, np.zeros((3, 1))])
    P = _matrix(P, (3, 4), "camera_info P")
    for name, b in (("binning_x", binning_x), ("binning_y", binning_y)):
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 0 <= b <= UINT32_MAX:
            raise InputError(f"camera_info {name}: expected a uint32 (0 = no binning), got {b!r}")
    types = _types()
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                    do_rectify=False)
    return types["sensor_msgs/msg/CameraInfo"](
        header=header(stamp_ns, frame_id), height=height, width=width,
        distortion_model=distortion_model, d=D, k=K.reshape(9).copy(), r=R.reshape(9).copy(),
        p=P.reshape(12).copy(), binning_x=int(binning_x), binning_y=int(binning_y), roi=roi)


def K_from_camera_info(msg) -> np.ndarray:
    """3x3 float64 intrinsic matrix of a CameraInfo message."""
    K = np.array(msg.k, dtype=np.float64)
    if K.shape != (9,):
        raise FormatError(f"CameraInfo.k has {K.size} values, expected 9", source="sensor_msgs/msg/CameraInfo")
    return K.reshape(3, 3)


def intrinsics_from_camera_info(msg) -> dict:
    """Everything a pinhole model needs: width, height, K (3x3), D, distortion_model, R, P, frame_id, stamp_ns."""
    return {
        "width": int(msg.width), "height": int(msg.height), "K": K_from_camera_info(msg),
        "D": np.array(msg.d, dtype=np.float64), "distortion_model": str(msg.distortion_model),
        "R": np.array(msg.r, dtype=np.float64).reshape(3, 3),
        "P": np.array(msg.p, dtype=np.float64).reshape(3, 4),
        "frame_id": str(msg.header.frame_id), "stamp_ns": header_stamp_ns(msg),
    }


# --------------------------------------------------------------------------- poses


def pose_stamped(T_world_cam, stamp_ns: int, frame_id: str = "world"):
    """``geometry_msgs/msg/PoseStamped`` of a 4x4 rigid transform (the pose of the child in frame_id)."""
    T = check_rigid(T_world_cam)
    types = _types()
    q = quat_to_ros(matrix_to_quat(T[:3, :3]))
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                          w=float(q[3])))
    return types["geometry_msgs/msg/PoseStamped"](header=header(stamp_ns, frame_id), pose=pose)


def pose_to_matrix(pose) -> np.ndarray:
    """``geometry_msgs/Pose`` -> 4x4 float64. A quaternion off unit length by more than
    QUAT_NORM_TOL (or not finite) raises FormatError; smaller deviations are normalised."""
    o, p = pose.orientation, pose.position
    q = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)
    t = np.array([p.x, p.y, p.z], dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))) or abs(n - 1.0) > QUAT_NORM_TOL:
        raise FormatError(f"pose has quaternion {q.tolist()} (norm {n:.6g}) / position {t.tolist()}: "
                          f"not a valid rigid pose (need finite values and |q| within {QUAT_NORM_TOL} of 1)",
                          source="geometry_msgs/msg/Pose")
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(quat_from_ros(q / n))
    T[:3, 3] = t
    return T


def pose_from_pose_stamped(msg) -> tuple[np.ndarray, int, str]:
    """PoseStamped -> (T 4x4 float64, stamp_ns, frame_id)."""
    return pose_to_matrix(msg.pose), header_stamp_ns(msg), str(msg.header.frame_id)


# --------------------------------------------------------------------------- JointState / TimeReference


def joint_state(names: Sequence[str], positions, velocities=None, *, stamp_ns: int, efforts=None,
                frame_id: str = ""):
    """``sensor_msgs/msg/JointState``; velocities / efforts may be omitted (empty, as ROS allows)."""
    if isinstance(names, str) or not all(isinstance(n, str) and n for n in names):
        raise InputError(f"joint_state names: expected a list of non-empty strings, got {names!r}")
    names = list(names)
    if len(set(names)) != len(names):
        raise InputError(f"joint_state names: duplicates in {names}")
    pos = _vector(positions, "joint_state positions", size=len(names))
    vel = _vector(velocities, "joint_state velocities",
                  size=None if velocities is None else len(names))
    eff = _vector(efforts, "joint_state efforts", size=None if efforts is None else len(names))
    return _types()["sensor_msgs/msg/JointState"](header=header(stamp_ns, frame_id), name=names,
                                                  position=pos, velocity=vel, effort=eff)


def time_reference(stamp_ns: int, time_ref_ns: int, source: str, *, frame_id: str = ""):
    """``sensor_msgs/msg/TimeReference``: header.stamp = host time, time_ref = the external clock's time."""
    if not isinstance(source, str):
        raise InputError(f"time_reference source: expected a string, got {type(source).__name__}")
    return _types()["sensor_msgs/msg/TimeReference"](
        header=header(stamp_ns, frame_id), time_ref=ns_to_stamp(time_ref_ns, what="time_ref"), source=source)


def time_reference_ns(msg) -> tuple[int, int, str]:
    """TimeReference -> (stamp_ns, time_ref_ns, source)."""
    return header_stamp_ns(msg), stamp_to_ns(msg.time_ref, what="TimeReference.time_ref"), str(msg.source)
