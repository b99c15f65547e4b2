"""Where the camera is, relative to the scene, for a turntable angle.

The rig's turntable (the firmware's D10 servo, 0..180 deg, home 90) turns the scene about the
world's vertical axis through the origin. Seen from the scene, that is the camera turning the
other way: ``T_world_cam(angle) = Rz(-(angle - home)) @ T_world_cam(home)``. The capture node
records each view's pose with this, and the virtual rig's camera twin renders from it.
"""

from __future__ import annotations

import math

import numpy as np


def turntable_pose(T_home, angle_deg: float, home_deg: float = 90.0) -> np.ndarray:
    """The camera pose (4x4 T_world_cam) when the turntable is at ``angle_deg``, given the pose
    ``T_home`` at ``home_deg``."""
    a = math.radians(-(float(angle_deg) - float(home_deg)))
    R = np.eye(4)
    R[0, 0], R[0, 1], R[1, 0], R[1, 1] = math.cos(a), -math.sin(a), math.sin(a), math.cos(a)
    return R @ np.asarray(T_home, np.float64)


def view_azimuth_deg(angle_deg: float, home_deg: float = 90.0) -> float:
    """The camera's azimuth on the rig's ring, relative to the home view, for a turntable angle."""
    return -(float(angle_deg) - float(home_deg))
