"""Rigid-body trajectories evaluated exactly at int64-ns times.

Rotations are quaternions in the toolkit's order ``(w, x, y, z)`` (see ``rotations``).

Interpolation (all evaluated from integer ns: the only float is the in-segment fraction
``u = (t_ns - t_k) / (t_{k+1} - t_k)``, an int64 difference divided by an int64 difference):

* **Position** (and scalar hinge angles): cubic Hermite per segment with finite-difference
  (Catmull-Rom style, non-uniform) tangents ``m_k = (d_{k-1} h_k + d_k h_{k-1}) / (h_{k-1} + h_k)``
  where ``d_k = (p_{k+1} - p_k) / h_k`` and ``h_k = t_{k+1} - t_k`` (exact for quadratics);
  end tangents are the one-sided slopes.  It passes through every keyframe exactly and is
  C1 inside the keyframe span; before the first / after the last keyframe the value is held.
* **Rotation**: a C1 quaternion spline in cumulative Bezier form (Kim, Kim & Shin 1995):
  with body angular velocities ``w_k`` at the keyframes (the same weighted finite difference
  applied to ``log(q_k^-1 q_{k+1}) / h_k``), the segment control rotations are
  ``qa = q_k exp(w_k h_k / 3)``, ``qb = q_{k+1} exp(-w_{k+1} h_k / 3)`` and
  ``q(u) = q_k exp(v1 B1(u)) exp(v2 B2(u)) exp(v3 B3(u))`` with ``v1 = log(q_k^-1 qa)``,
  ``v2 = log(qa^-1 qb)``, ``v3 = log(qb^-1 q_{k+1})`` and the cumulative Bernstein
  polynomials ``B1 = 1 - (1-u)^3``, ``B2 = 3u^2 - 2u^3``, ``B3 = u^3``.  It interpolates the
  keyframes exactly, its angular velocity is continuous (C1), and for two keyframes it
  reduces to ``slerp`` exactly.  Consecutive keyframes must differ by less than 180 deg
  (the shortest arc is taken): for a full turn give at least three intermediate keyframes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import InputError
from .poses import check_increasing_times, rigid
from .rotations import quat_conj, quat_exp, quat_from_axis_angle, quat_log, quat_mul, quat_normalize, quat_to_matrix

# ----------------------------------------------------------------------------- splines

def _check_times(times_ns) -> np.ndarray:
    return check_increasing_times(times_ns, "trajectory", item="keyframe")


def _segment(times: np.ndarray, t_ns: int) -> tuple[int, float]:
    """Segment index k and fraction u in [0, 1] (held outside the span)."""
    t = int(t_ns)
    if t <= times[0] or times.size == 1:
        return 0, 0.0
    if t >= times[-1]:
        return times.size - 2, 1.0
    k = int(np.searchsorted(times, t, side="right")) - 1
    return k, (t - int(times[k])) / (int(times[k + 1]) - int(times[k]))


def _fd_tangents(times_s: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Weighted 3-point finite-difference tangents (per second)."""
    n = values.shape[0]
    if n == 1:
        return np.zeros_like(values)
    h = np.diff(times_s)
    d = np.diff(values, axis=0) / h[:, None]
    m = np.empty_like(values)
    m[0], m[-1] = d[0], d[-1]
    if n > 2:
        hp, hn = h[:-1, None], h[1:, None]
        m[1:-1] = (d[:-1] * hn + d[1:] * hp) / (hp + hn)
    return m


class HermiteSpline:
    """C1 cubic Hermite interpolation of vectors (K, D) at int64-ns keyframe times."""

    def __init__(self, times_ns, values):
        self.times = _check_times(times_ns)
        v = np.asarray(values, dtype=np.float64)
        self.values = v.reshape(self.times.size, -1)
        # seconds relative to the first keyframe, from integer differences
        rel_s = (self.times - self.times[0]) * 1e-9
        self.tangents = _fd_tangents(rel_s, self.values)

    def __call__(self, t_ns) -> np.ndarray:
        if self.times.size == 1:
            return self.values[0].copy()
        k, u = _segment(self.times, t_ns)
        h = (int(self.times[k + 1]) - int(self.times[k])) * 1e-9
        u2, u3 = u * u, u * u * u
        h00 = 2 * u3 - 3 * u2 + 1
        h10 = u3 - 2 * u2 + u
        h01 = -2 * u3 + 3 * u2
        h11 = u3 - u2
        return (h00 * self.values[k] + h10 * h * self.tangents[k]
                + h01 * self.values[k + 1] + h11 * h * self.tangents[k + 1])


class RotationSpline:
    """C1 quaternion spline through keyframe rotations (cumulative Bezier form)."""

    def __init__(self, times_ns, quats):
        self.times = _check_times(times_ns)
        q = quat_normalize(np.asarray(quats, dtype=np.float64).reshape(-1, 4))
        if q.shape[0] != self.times.size:
            raise InputError("one rotation per keyframe is needed")
        for k in range(1, q.shape[0]):               # shortest arcs between neighbours
            if np.dot(q[k - 1], q[k]) < 0:
                q[k] = -q[k]
        self.quats = q
        n = q.shape[0]
        if n == 1:
            return
        h = np.diff(self.times) * 1e-9
        rel = np.stack([quat_log(quat_mul(quat_conj(q[k]), q[k + 1])) for k in range(n - 1)])
        d = rel / h[:, None]                          # body angular velocity per segment
        w = np.empty((n, 3))
        w[0], w[-1] = d[0], d[-1]
        if n > 2:
            hp, hn = h[:-1, None], h[1:, None]
            w[1:-1] = (d[:-1] * hn + d[1:] * hp) / (hp + hn)
        self.omega = w
        self.v = np.empty((n - 1, 3, 3))
        for k in range(n - 1):
            qa = quat_mul(q[k], quat_exp(w[k] * h[k] / 3.0))
            qb = quat_mul(q[k + 1], quat_exp(-w[k + 1] * h[k] / 3.0))
            self.v[k, 0] = w[k] * h[k] / 3.0
            self.v[k, 1] = quat_log(quat_mul(quat_conj(qa), qb))
            self.v[k, 2] = w[k + 1] * h[k] / 3.0

    def __call__(self, t_ns) -> np.ndarray:
        if self.times.size == 1:
            return self.quats[0].copy()
        k, u = _segment(self.times, t_ns)
        om = 1.0 - u
        b = (1.0 - om * om * om, 3 * u * u - 2 * u * u * u, u * u * u)
        q = self.quats[k]
        for j in range(3):
            q = quat_mul(q, quat_exp(self.v[k, j] * b[j]))
        return q / np.linalg.norm(q)


@dataclass
class KeyframeTrajectory:
    """Rigid motion through keyframes: T(t) = [R(q(t)) | p(t)] in the parent frame."""

    times_ns: np.ndarray
    positions: np.ndarray           # (K, 3) metres
    quats: np.ndarray               # (K, 4) w, x, y, z

    def __post_init__(self):
        self._pos = HermiteSpline(self.times_ns, self.positions)
        self._rot = RotationSpline(self.times_ns, self.quats)
        self.times_ns = self._pos.times

    def position(self, t_ns) -> np.ndarray:
        return self._pos(t_ns)

    def rotation(self, t_ns) -> np.ndarray:
        return self._rot(t_ns)

    def __call__(self, t_ns) -> np.ndarray:
        return rigid(quat_to_matrix(self._rot(t_ns)), self._pos(t_ns))

    @property
    def span_ns(self) -> tuple[int, int]:
        return int(self.times_ns[0]), int(self.times_ns[-1])


@dataclass
class HingeMotion:
    """Rotation by angle(t) (radians) about ``axis`` through ``pivot`` (parent frame)."""

    axis: np.ndarray
    pivot: np.ndarray
    angle_rad: Callable[[int], float]
    span_ns: tuple[int, int] | None = None     # where the angle changes (None: unknown)

    def __post_init__(self):
        a = np.asarray(self.axis, dtype=np.float64)
        self.axis = a / np.linalg.norm(a)
        self.pivot = np.asarray(self.pivot, dtype=np.float64)

    def __call__(self, t_ns) -> np.ndarray:
        R = quat_to_matrix(quat_from_axis_angle(self.axis, self.angle_rad(t_ns)))
        return rigid(R, self.pivot - R @ self.pivot)


class AngleKeyframes:
    """C1 interpolation of scalar angles (radians) at keyframe times (picklable callable)."""

    def __init__(self, times_ns, angles_rad):
        self.spline = HermiteSpline(times_ns, np.asarray(angles_rad, dtype=np.float64)[:, None])

    def __call__(self, t_ns) -> float:
        return float(self.spline(t_ns)[0])


def angle_keyframes(times_ns, angles_rad) -> AngleKeyframes:
    return AngleKeyframes(times_ns, angles_rad)
