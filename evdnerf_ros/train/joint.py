"""The rig's joint for the ``hinge`` field: where the servo axis is and its angle over time.

A training set converted from a simulated session or a virtual-rig capture records its true
scene (``truth``: scene file and the scene time at the common clock's origin, per view). Its one
hinged object gives the joint: pivot and axis in the world (through its parent's pose) and the
angle at every moment of the training span. A real rig knows the same: the servo's mounting
(rig geometry) and the firmware's motion profile.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

#: Angle samples over the training span (linear between them: ~5 ms apart over 1.2 s, where
#: the servo's minimum-jerk profile deviates from a chord by < 0.02 degree).
ANGLE_SAMPLES = 257


def hinged_part(train_set):
    """(the true scene, its one hinged object, the truth record), or an InputError saying why
    the set has no joint (the fix: backbone planes)."""
    from ..geometry.trajectory import HingeMotion
    from ..sim.scene import load_scene

    where = f"{train_set.path}: backbone hinge"
    record = train_set.provenance.get("truth")
    if not record:
        raise InputError(f"{where}: the training set records no scene, so its joint is unknown "
                         "(simulated and virtual-rig sets only); train with backbone planes")
    scene = load_scene(record["scene"], check_cameras=False)
    hinged = [o for o in scene.all_objects() if isinstance(o.motion, HingeMotion)]
    moving = [o for o in scene.all_objects() if o.motion is not None]
    if len(hinged) != 1 or len(moving) != 1:
        raise InputError(f"{where}: scene {scene.name!r} has {len(hinged)} hinged and {len(moving)} moving "
                         "objects; the hinge field models exactly one joint and nothing else moving "
                         "(train with backbone planes)")
    return scene, hinged[0], record


def joint_from_training_set(train_set, box, samples: int = ANGLE_SAMPLES) -> dict:
    """``HingeField``'s ``joint`` from the true scene of ``train_set`` (see the module notes)."""
    scene, part, record = hinged_part(train_set)
    parent = np.eye(4) if part.parent is None else scene.transforms(scene.start_ns)[part.parent]
    pivot = parent[:3, :3] @ part.motion.pivot + parent[:3, 3]
    axis = parent[:3, :3] @ part.motion.axis
    lo, hi = (np.asarray(b, np.float64) for b in box)
    origins = np.array([int(v) for v in record["scene_time_at_origin_ns"].values()], np.int64)
    # views agree on the scene time at the origin up to the sync error; the median is the joint's
    origin = int(np.median(origins))
    t0, t1 = (int(v) for v in train_set.time_range)
    t_ns = t0 + np.round(np.linspace(0.0, 1.0, int(samples)) * (t1 - t0)).astype(np.int64)
    angles = [float(part.motion.angle_rad(int(t) + origin)) for t in t_ns]
    return {"pivot": ((pivot - lo) / (hi - lo) * 2.0 - 1.0).tolist(), "axis": axis.tolist(),
            "half": ((hi - lo) / 2.0).tolist(), "angles_rad": angles}
