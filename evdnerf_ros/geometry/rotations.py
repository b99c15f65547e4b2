"""Rotations as unit quaternions.

One order inside the toolkit: ``(w, x, y, z)`` float64, unit norm, acting on column vectors
(``v_world = R(q) @ v_local``).  ROS messages carry ``(x, y, z, w)``: convert only at that
boundary, with ``quat_from_ros`` / ``quat_to_ros``.  Rotation vectors ("rotvec") are
axis * angle in radians.
"""

from __future__ import annotations

import numpy as np


def quat_normalize(q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    return q / n


def quat_mul(a, b) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_conj(q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_exp(rotvec) -> np.ndarray:
    """Unit quaternion of the rotation by |rotvec| radians about rotvec."""
    v = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half)/angle, with its series near 0
    small = angle < 1e-8
    k = np.where(small, 0.5 - angle * angle / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), v * k], axis=-1)


def quat_log(q) -> np.ndarray:
    """Rotation vector of a unit quaternion, taking the shortest arc (angle in [0, pi])."""
    q = np.asarray(q, dtype=np.float64)
    q = np.where(q[..., :1] < 0, -q, q)
    w = np.clip(q[..., :1], -1.0, 1.0)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, w)
    small = s < 1e-12
    k = np.where(small, 2.0 / np.where(w == 0, 1.0, w), angle / np.where(small, 1.0, s))
    return v * k


def quat_from_axis_angle(axis, angle_rad) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return quat_exp(axis * float(angle_rad))


def quat_to_matrix(q) -> np.ndarray:
    """(..., 4) quaternions -> (..., 3, 3) rotation matrices."""
    w, x, y, z = np.moveaxis(quat_normalize(q), -1, 0)
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1).reshape(*w.shape, 3, 3)


def matrix_to_quat(R) -> np.ndarray:
    """Unit quaternion (w >= 0) of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = quat_normalize(q)
    return -q if q[0] < 0 else q


def quat_from_euler_deg(angles_deg) -> np.ndarray:
    """Euler angles in degrees (x, y, z), extrinsic XYZ (Blender's 'XYZ'): R = Rz @ Ry @ Rx."""
    ax, ay, az = np.radians(np.asarray(angles_deg, dtype=np.float64))
    qx = quat_from_axis_angle([1, 0, 0], ax)
    qy = quat_from_axis_angle([0, 1, 0], ay)
    qz = quat_from_axis_angle([0, 0, 1], az)
    return quat_mul(qz, quat_mul(qy, qx))


def slerp(q0, q1, u) -> np.ndarray:
    """Spherical linear interpolation along the shortest arc: one pair (4,) with u scalar or an
    array (...), or pairs (..., 4) with u (...)."""
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    q1 = np.where(np.sum(q0 * q1, axis=-1, keepdims=True) < 0, -q1, q1)
    rel = quat_log(quat_mul(quat_conj(q0), q1))
    u = np.asarray(u, dtype=np.float64)
    return quat_mul(q0, quat_exp(rel * u[..., None]))


def quat_from_ros(q_xyzw) -> np.ndarray:
    """ROS order (x, y, z, w) -> the toolkit's (w, x, y, z)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def quat_to_ros(q_wxyz) -> np.ndarray:
    """The toolkit's (w, x, y, z) -> ROS order (x, y, z, w)."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)
