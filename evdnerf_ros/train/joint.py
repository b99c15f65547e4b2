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


def part_box(joint: dict, region_mask, margin_cells: float = 1.0) -> list | None:
    """The box that can hold the hinge field's moving part, in its frame (``HingeField``:
    box-normalised, axes of the world): [[lo x, y, z], [hi x, y, z]], or None for an empty region.

    Every point of the part lies, at every time, inside the dynamic region (the part's changes
    carve it), and turning about the joint keeps a point's position along the axis and its
    distance from it: so in the part's frame the part lies inside the cylinder about the axis
    that spans the region's cells along it and reaches its farthest cell; the box is that
    cylinder's bounding box, within the scene box. Each cell centre counts with half a cell
    diagonal times ``margin_cells`` + 1 of margin. A servo's fork swings in one plane, so the
    box is thin along the axis (a quarter of the scene box's width on the demo's fork), and the
    same planes resolve the part's thickness that much finer. Stray specks of the region
    (``main_components``) are left out first: a cell in a corner of the box would stretch it.
    (The box of the region turned back at each angle, intersected over the angles, is tighter
    across the axis too; measured, it broke the side-on views' fit: docs/training.md, "The part's own box".)"""
    mask = np.asarray(region_mask, bool)
    if mask.ndim != 3:
        raise ValueError(f"part box: the dynamic region must be a 3D grid, got shape {mask.shape}")
    mask = main_components(mask)
    if not mask.any():
        return None
    res = np.asarray(mask.shape, np.float64)
    half = np.asarray(joint["half"], np.float64)
    pivot = np.asarray(joint["pivot"], np.float64)
    axis = np.asarray(joint["axis"], np.float64)
    axis = axis / np.linalg.norm(axis)
    centres = -1.0 + (2.0 * np.argwhere(mask) + 1.0) / res               # box-normalised
    w = (centres - pivot) * half                                          # metres about the pivot
    along = w @ axis
    radius = float(np.linalg.norm(w - np.outer(along, axis), axis=1).max())
    pad = (1.0 + margin_cells) * 0.5 * float(np.linalg.norm(2.0 * half / res))
    ends = np.stack([(along.min() - pad) * axis, (along.max() + pad) * axis])
    across = (radius + pad) * np.sqrt(np.clip(1.0 - axis ** 2, 0.0, None))
    lo = np.maximum(ends.min(0) - across, -half - pivot * half) / half + pivot
    hi = np.minimum(ends.max(0) + across, half - pivot * half) / half + pivot
    return [lo.tolist(), hi.tolist()]


def part_box_pays(train_set, box, joint: dict, finest: int) -> bool:
    """``part_box: auto``: whether the training views see the part finer than the scene box's
    finest planes resolve it along the joint's axis: the footprint of a pixel at the pivot
    (distance over focal length, the median over the static training views) smaller than one
    of those cells. Where it is not, finer cells buy nothing (measured: the virtual rig's 48x36
    set, 6.4 cm pixels against 4.4 cm cells, closed 1-3 points less with the box; the demo's
    96x72 set, 3.2 cm pixels, more on every seed: docs/training.md, "The part's own box")."""
    lo, hi = (np.asarray(b, np.float64) for b in box)
    half = (hi - lo) / 2.0
    pivot = lo + (np.asarray(joint["pivot"], np.float64) + 1.0) * half
    axis = np.abs(np.asarray(joint["axis"], np.float64))
    cell = float(axis / np.linalg.norm(axis) @ (2.0 * half / int(finest)))
    footprints = [np.linalg.norm(train_set.pose(v)[:3, 3] - pivot) / float(train_set.K(v)[0, 0])
                  for v in train_set.train_views if train_set.poses(v) is None]
    return bool(footprints) and float(np.median(footprints)) < cell


def main_components(mask: np.ndarray, keep_fraction: float = 0.05) -> np.ndarray:
    """``mask`` (3D bool) keeping only its connected parts (26-neighbourhood) of at least
    ``keep_fraction`` of the largest one's cells: a carved region's specks (corners of the box no
    view sees closely) dropped, its body and anything sizeable beside it kept."""
    cells = {tuple(c) for c in np.argwhere(mask).tolist()}
    offsets = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
    parts = []
    while cells:
        seed = cells.pop()
        part, todo = [seed], [seed]
        while todo:
            x, y, z = todo.pop()
            for a, b, c in offsets:
                n = (x + a, y + b, z + c)
                if n in cells:
                    cells.remove(n)
                    part.append(n)
                    todo.append(n)
        parts.append(part)
    out = np.zeros_like(mask, dtype=bool)
    if parts:
        largest = max(len(p) for p in parts)
        for p in parts:
            if len(p) >= keep_fraction * largest:
                out[tuple(np.asarray(p).T)] = True
    return out
