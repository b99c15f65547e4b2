"""Interpolated robot trajectory from timestamped poses: linear position, slerp rotation.

``PoseTrack(t_ns, T)(t) -> 4x4`` for ``t`` inside the track; a gap longer than
``max_gap_ns`` between two poses is refused (interpolating across it would invent motion).
Times are int64 ns; the in-segment fraction is a float from int64 differences.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .poses import check_increasing_times
from .rotations import matrix_to_quat, quat_conj, quat_exp, quat_log, quat_mul, quat_normalize, quat_to_matrix


class PoseTrack:
    def __init__(self, t_ns, T, *, max_gap_ns: int | None = None, source: str = "trajectory"):
        t = np.asarray(t_ns, dtype=np.int64)
        T = np.asarray(T, dtype=np.float64)
        if t.ndim != 1 or T.shape != (t.size, 4, 4) or t.size < 2:
            raise InputError(f"{source}: need >= 2 times and as many 4x4 poses (got {t.shape}, {T.shape})")
        dt = np.diff(check_increasing_times(t, source, min_count=2))
        if max_gap_ns is not None and np.any(dt > max_gap_ns):
            i = int(np.argmax(dt))
            raise InputError(f"{source}: gap of {dt[i] / 1e9:.3f} s between pose {i} (t={int(t[i])} ns) and "
                             f"pose {i + 1}, longer than max_gap {max_gap_ns / 1e9:g} s; interpolating across it "
                             "would invent motion: fill the gap, split the trajectory, or raise trajectory_max_gap")
        self.source = source
        self.t = t
        self.p = T[:, :3, 3].copy()
        q = np.array([matrix_to_quat(R) for R in T[:, :3, :3]])
        for i in range(1, len(q)):               # one hemisphere: slerp takes the short arc
            if np.dot(q[i], q[i - 1]) < 0:
                q[i] = -q[i]
        self.q = quat_normalize(q)
        # each segment's rotation as a log (slerp's shortest arc, the hemisphere fixed above), made
        # once: a pose is then one exp and one product
        self.rel = quat_log(quat_mul(quat_conj(self.q[:-1]), self.q[1:]))

    @property
    def span_ns(self) -> tuple[int, int]:
        return int(self.t[0]), int(self.t[-1])

    def __call__(self, t_ns) -> np.ndarray:
        return self.poses([int(t_ns)])[0]

    def poses(self, t_ns) -> np.ndarray:
        """(K, 4, 4) poses at the times ``t_ns`` ((K,) int64 ns, inside the track)."""
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        outside = np.flatnonzero((t < self.t[0]) | (t > self.t[-1]))
        if outside.size:
            raise InputError(f"{self.source}: time {int(t[outside[0]])} ns is outside the trajectory "
                             f"[{int(self.t[0])}, {int(self.t[-1])}] ns")
        i = np.minimum(np.searchsorted(self.t, t, "right") - 1, self.t.size - 2)
        u = (t - self.t[i]) / (self.t[i + 1] - self.t[i]).astype(np.float64)
        T = np.zeros((t.size, 4, 4))
        T[:, 3, 3] = 1.0
        T[:, :3, :3] = quat_to_matrix(quat_mul(self.q[i], quat_exp(self.rel[i] * u[:, None])))
        T[:, :3, 3] = self.p[i] + u[:, None] * (self.p[i + 1] - self.p[i])
        return T
