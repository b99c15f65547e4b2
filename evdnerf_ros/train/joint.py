"""The rig's joint for the ``hinge`` field: where the servo axis is and its angle over time.

The rig knows both: the servo's mounting (axis and pivot in the world) and how it turns after
its start (the firmware's profile). The simulator and the virtual rig write them into
session.yaml's ``servo`` section (``sim.joint``); convert carries them into the training set as
``joint``, with the servo's start on the common clock. Here they become ``HingeField``'s
``joint``: the pivot in box-normalised coordinates and the angle sampled over the training span.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

#: Angle samples over the training span (linear between them: ~5 ms apart over 1.2 s, where
#: the servo's minimum-jerk profile deviates from a chord by < 0.02 degree).
ANGLE_SAMPLES = 257


def recorded_joint(train_set) -> dict:
    """The training set's ``joint`` record, or an InputError saying why there is none (the fix:
    backbone planes)."""
    joint = train_set.provenance.get("joint")
    if not joint:
        raise InputError(f"{train_set.path}: backbone hinge needs the rig's joint, and the training set records "
                         "none (a session converted from a simulation or the virtual rig by this version "
                         "records it when a servo hinge is the scene's only motion); train with backbone planes")
    return joint


def joint_from_training_set(train_set, box, samples: int = ANGLE_SAMPLES) -> dict:
    """``HingeField``'s ``joint`` from the set's record (module notes), for the scene ``box``."""
    joint = recorded_joint(train_set)
    lo, hi = (np.asarray(b, np.float64) for b in box)
    pivot = np.asarray(joint["pivot"], np.float64)
    t0, t1 = (int(v) for v in train_set.time_range)
    t_ns = t0 + np.round(np.linspace(0.0, 1.0, int(samples)) * (t1 - t0)).astype(np.int64)
    values = np.asarray(joint["angles_rad"], np.float64)
    # the angle before the start is the first sample's, after the profile's end the last one's
    elapsed = (t_ns - np.int64(joint["start_ns"])).astype(np.float64) / float(joint["step_ns"])
    angles = np.interp(elapsed, np.arange(values.size, dtype=np.float64), values)
    return {"pivot": ((pivot - lo) / (hi - lo) * 2.0 - 1.0).tolist(), "axis": list(joint["axis"]),
            "half": ((hi - lo) / 2.0).tolist(), "angles_rad": angles.tolist()}
