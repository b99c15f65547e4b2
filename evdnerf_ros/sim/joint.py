"""What a rig knows about its one joint, for session.yaml's ``servo`` section.

A rig whose only motion is one servo hinge knows where the servo's axis is (its mounting: a
point on the axis and the axis direction, world frame) and how it turns after START (the
firmware's profile). The simulator and the virtual rig write that down from their scene; convert
carries it into the training set (``joint``), where the ``hinge`` field reads it.
"""

from __future__ import annotations

import numpy as np

from ..geometry.trajectory import HingeMotion

#: The angle is written every millisecond after the servo's start (a minimum-jerk swing of 45
#: degrees in 250 ms departs from its chords by < 0.001 degree at that spacing).
ANGLE_STEP_NS = 1_000_000


def joint_record(scene) -> dict | None:
    """``{"axis", "pivot", "angle_rad": {"step_ns", "values"}}``: the scene's one servo hinge in
    the world (``values[k]``: the angle ``k * step_ns`` after the servo's start, held after the
    last), or None when the scene moves anything else, or nothing, or moves its hinge's parent."""
    moving = [o for o in scene.all_objects() if o.motion is not None]
    if len(moving) != 1 or moving[0].servo is None or not isinstance(moving[0].motion, HingeMotion):
        return None
    part = moving[0]
    parent = np.eye(4) if part.parent is None else scene.transforms(scene.start_ns)[part.parent]
    drive = part.servo
    steps = -(-int(drive.profile.duration_ns) // ANGLE_STEP_NS) + 1
    values = [drive.angle_rad(drive.start_ns + k * ANGLE_STEP_NS) for k in range(steps)]
    return {"axis": (parent[:3, :3] @ part.motion.axis).tolist(),
            "pivot": (parent[:3, :3] @ part.motion.pivot + parent[:3, 3]).tolist(),
            "angle_rad": {"step_ns": ANGLE_STEP_NS, "values": [float(v) for v in values]}}


class ServoTrack:
    """A servo's angle (degrees) at times (ns) joined linearly, held beyond the ends, as the hinge's
    angle (radians) from the servo's ``zero_deg``: what the virtual rig's camera twin rendered (the
    firmware's commands as they reached it), in place of the stored profile. Picklable."""

    def __init__(self, t_ns, deg, zero_deg: float):
        self.t = np.asarray(t_ns, np.int64)
        self.deg = np.asarray(deg, np.float64)
        if self.t.ndim != 1 or self.t.shape != self.deg.shape or not self.t.size:
            raise ValueError(f"a servo track needs equal, non-empty lists of times and angles, got "
                             f"{self.t.shape} and {self.deg.shape}")
        self.zero_deg = float(zero_deg)

    def __call__(self, t_ns) -> float:
        return float(np.radians(np.interp(float(t_ns), self.t.astype(np.float64), self.deg) - self.zero_deg))


def follow_servo_track(scene, t_ns, deg) -> None:
    """Make ``scene``'s one servo hinge follow the angles ``deg`` (the servo's degrees) at scene
    times ``t_ns`` instead of its profile."""
    servos = [o for o in scene.all_objects() if o.servo is not None and isinstance(o.motion, HingeMotion)]
    if len(servos) != 1:
        raise ValueError(f"{scene.source}: a servo track drives a scene's one servo hinge; it has {len(servos)}")
    part = servos[0]
    track = ServoTrack(t_ns, deg, part.servo.zero_deg)
    part.motion = HingeMotion(part.motion.axis, part.motion.pivot, track, (int(track.t[0]), int(track.t[-1])))
