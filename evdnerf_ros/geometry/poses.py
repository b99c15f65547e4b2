"""Rigid poses: building them, the one rigidity check, and the one monotonic-times check.

A pose is ``T_a_b``: a 4x4 float64 matrix mapping b-coordinates to a-coordinates, rotation
block orthonormal with det +1, last row ``0 0 0 1``.  Every reader of poses (messages,
trajectory files, session.yaml, training sets, renderers) checks through ``check_rigid`` so
that one tolerance and one message apply everywhere.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

#: Tolerance on |R^T R - I| and |det R - 1| when accepting a pose as rigid.
RIGID_TOL = 1e-6


def rigid(R=None, p=None) -> np.ndarray:
    """4x4 transform from a rotation matrix and a translation (either may be left out)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if p is not None:
        T[:3, 3] = p
    return T


def check_rigid(T, what: str = "T_world_cam", *, tol: float = RIGID_TOL) -> np.ndarray:
    """T (4x4) or a stack (M, 4, 4) as float64; InputError naming the first pose that is not a
    finite proper rigid transform."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{what}: not a numeric 4x4 matrix") from None
    single = T.ndim == 2
    stack = T[None] if single else T
    if stack.ndim != 3 or stack.shape[1:] != (4, 4):
        raise InputError(f"{what}: expected a 4x4 matrix{'' if single else ' stack (M, 4, 4)'}, "
                         f"got shape {T.shape}")
    finite = np.all(np.isfinite(stack.reshape(len(stack), -1)), axis=1)
    R = np.where(finite[:, None, None], stack[:, :3, :3], np.eye(3))
    with np.errstate(all="ignore"):              # absurd entries: the checks below say so
        err = np.abs(np.einsum("mji,mjk->mik", R, R) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(R)
    last = np.all(stack[:, 3] == [0.0, 0.0, 0.0, 1.0], axis=1)
    bad = np.flatnonzero(~finite | (err > tol) | (np.abs(det - 1) > tol) | ~last)
    if bad.size:
        i = int(bad[0])
        name = what if single else f"{what}[{i}]"
        if not finite[i]:
            raise InputError(f"{name}: not a rigid transform: contains NaN or inf; every pose must be finite")
        if not last[i]:
            raise InputError(f"{name}: not a rigid transform: last row must be [0, 0, 0, 1], "
                             f"got {stack[i, 3].tolist()}")
        raise InputError(f"{name}: not a rigid transform: the rotation block is not a proper rotation, "
                         f"orthonormal with det +1 (|R^T R - I| = {err[i]:.3g}, det = {det[i]:.6g}; "
                         f"tolerance {tol:g}); re-orthonormalise it (e.g. via SVD) or fix the axis convention "
                         "(a reflection has det -1)")
    return T


def check_increasing_times(t_ns, what: str, *, item: str = "pose", min_count: int = 1) -> np.ndarray:
    """int64 times as a 1-D array; InputError unless there are >= min_count and each comes strictly
    after the one before (names the first offender)."""
    t = np.asarray(t_ns, dtype=np.int64).ravel()
    if t.size < min_count:
        raise InputError(f"{what}: {t.size} {item}(s); need at least {min_count} timestamped {item}s")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise InputError(f"{what}: {item} {i} at t={int(t[i])} ns does not come after {item} {i - 1} at "
                         f"t={int(t[i - 1])} ns; times must increase strictly (sort them, drop duplicates)")
    return t
