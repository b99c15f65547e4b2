"""How far anything can move in the image: the adaptive sampler's motion guard.

The sampler's midpoint test sees three images of a piece; a motion that goes there and
back (a servo swing, a periodic texture) between them is invisible to it. The scene knows
its motion, though, and evaluating transforms costs nothing next to rendering. So for a
view this module samples the motion densely (every sampler grid step, and at every
keyframe and servo segment boundary) and sums, per sample interval, a bound on the image
displacement of any surface point; ``ImageTravel(a, b)`` is the sum over the intervals
that [a, b] touches. The sampler splits any piece whose travel exceeds ``max_travel_px``,
so the midpoint test is only ever trusted over sub-pixel motion.

The bound per interval, per object: the largest displacement of a corner of its local
bounding box in the camera frame (exact for every point of the box: a rigid motion moves
points affinely, so the largest move is at a corner) over the smallest distance from the
camera to its bounding sphere gives an angle; angles become pixels with the camera's
largest magnification ``f (1 + tan^2 theta)`` (theta at the image corner). A moving camera
adds its rotation angle (the background at infinity). What this does not see: shadows move
with their casters but, on a surface at a grazing angle to the light, faster than them
(covered by the midpoint test and --min-step only).

``box_travel`` is the same bound for a trained field seen by a moving camera (the event
publisher): all it shows is a static box (and, with a learned background, what lies at
infinity); the field's own motion inside the box is unknown, so ``max_step`` must stay below it.
Without a background at infinity it also knows where the box can be seen (``ImageTravel.reach``):
the per-pixel sampler then splits a piece that travels too far only for the pixels the box
can reach during it; every other pixel shows the flat world throughout.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

#: Motion samples per view at most (transforms only, ~0.3 ms each for a 10-part scene).
MAX_MOTION_SAMPLES = 10_000
#: Every knot interval (between keyframes / servo segment boundaries) gets this many samples.
SAMPLES_PER_KNOT_INTERVAL = 8


class ImageTravel:
    """``travel(a, b)``: bound on the image travel (pixels) of any point during [a, b].
    With ``boxes`` ((K, 4) x0 y0 x1 y1 per sample time: the image box of everything that can
    change, NaN where it is not bounded), ``reach(a, b)`` says where a change may show."""

    def __init__(self, times: np.ndarray, cumulative_px: np.ndarray, boxes: np.ndarray | None = None):
        self.times = times
        self.cumulative = cumulative_px
        self.boxes = boxes

    def _span(self, a, b) -> tuple[np.ndarray, np.ndarray]:
        # whole sample intervals touching [a, b]: conservative between samples
        i = np.maximum(np.searchsorted(self.times, a, side="right") - 1, 0)
        j = np.minimum(np.searchsorted(self.times, b, side="left"), self.times.size - 1)
        return i, j

    def __call__(self, a: int, b: int) -> float:
        return float(self.many(a, b))

    def many(self, a, b) -> np.ndarray:
        """The travel of each piece [a[k], b[k]] (int64 arrays) at once (``travels``)."""
        i, j = self._span(a, b)
        return self.cumulative[j] - self.cumulative[i]

    def reach(self, a, b) -> np.ndarray | None:
        """(N, 4) x0 y0 x1 y1 (pixels, inclusive; +-inf: anywhere) of the pieces [a[k], b[k]]:
        the image box of what can change at the last sample time at or before a, grown by the
        travel from there to b, so every pixel whose value can change during the piece is in it;
        None without boxes."""
        if self.boxes is None:
            return None
        i, j = self._span(np.asarray(a, np.int64), np.asarray(b, np.int64))
        grow = (self.cumulative[j] - self.cumulative[i])[:, None] + 1.0      # + a pixel's footprint
        box = self.boxes[i] + grow * np.array([-1.0, -1.0, 1.0, 1.0])
        return np.where(np.isnan(box), np.array([-np.inf, -np.inf, np.inf, np.inf]), box)

    @property
    def total_px(self) -> float:
        return float(self.cumulative[-1])


def motion_sample_times(t0: int, t1: int, step_ns: int, knots=()) -> np.ndarray:
    """Sample times on [t0, t1]: a grid of `step_ns` (coarsened to MAX_MOTION_SAMPLES), the
    knots inside, and SAMPLES_PER_KNOT_INTERVAL points in every knot interval."""
    span = t1 - t0
    step = max(int(step_ns), -(-span // MAX_MOTION_SAMPLES), 1)
    parts = [np.arange(t0, t1, step, dtype=np.int64), np.array([t1], np.int64)]
    k = np.asarray(sorted(set(int(x) for x in knots if t0 < x < t1)), np.int64)
    if k.size:
        edges = np.concatenate([[t0], k, [t1]])
        sub = np.arange(1, SAMPLES_PER_KNOT_INTERVAL, dtype=np.int64)
        parts += [k, (edges[:-1, None] + (np.diff(edges)[:, None] * sub)
                      // SAMPLES_PER_KNOT_INTERVAL).ravel()]
    return np.unique(np.concatenate(parts))


def image_travel(scene, camera, pose_at: Callable[[int], np.ndarray], t0: int, t1: int,
                 step_ns: int) -> ImageTravel:
    """The motion guard of one view of `scene` (poses from `pose_at`) over [t0, t1]."""
    times = motion_sample_times(t0, t1, step_ns, scene.motion_knots_ns())
    leaves = scene.leaves
    corners = np.stack([o.shape.corners() for o in leaves])            # (L, 8, 3) local
    spheres = [o.shape.bounding_sphere() for o in leaves]
    centres = np.stack([c for c, _ in spheres])                        # (L, 3) local
    radii = np.array([r for _, r in spheres])
    px_per_rad = _magnification(camera)
    prev = None
    steps = np.zeros(times.size)
    for n, t in enumerate(times):
        t = int(t)
        T = np.asarray(pose_at(t), np.float64)
        Rc, c = T[:3, :3], T[:3, 3]
        tfs = np.stack(scene.leaf_transforms(t))                        # (L, 4, 4)
        R, p = tfs[:, :3, :3], tfs[:, :3, 3]
        # corners and sphere centres in the camera frame
        pc = (np.einsum("lij,lkj->lki", R, corners) + p[:, None, :] - c) @ Rc
        sc = (np.einsum("lij,lj->li", R, centres) + p - c) @ Rc
        cur = (pc, np.linalg.norm(sc, axis=1) - radii, Rc)
        if prev is not None:
            move = np.linalg.norm(pc - prev[0], axis=2).max(axis=1)      # (L,) metres
            near = np.minimum(cur[1], prev[1])
            with np.errstate(divide="ignore", invalid="ignore"):
                ang = np.where(move == 0, 0.0,
                               np.where(near > move, move / np.maximum(near - move, 1e-300),
                                        math.pi))
            cam_rot = _rotation_angle(prev[2].T @ Rc)
            steps[n] = max(min(float(ang.max(initial=0.0)), math.pi), cam_rot) * px_per_rad
        prev = cur
    return ImageTravel(times, np.cumsum(steps))


def travels(travel_px: ImageTravel | Callable[[int, int], float], a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K,) image travel bounds of the pieces [a[k], b[k]]: an ``ImageTravel``'s in one vectorised
    pass (``many``), any other ``travel_px(a, b)`` callable's piece by piece."""
    if isinstance(travel_px, ImageTravel):
        return np.asarray(travel_px.many(np.asarray(a, np.int64), np.asarray(b, np.int64)), np.float64)
    return np.array([travel_px(int(x), int(y)) for x, y in zip(a, b)], np.float64)


def box_travel(box, camera, times: np.ndarray, poses: np.ndarray, *, infinity: bool = True) -> ImageTravel:
    """The motion guard of a camera moving past a static box ((2, 3) world lo / hi): what a trained
    field shows lies in it (and, with ``infinity``, a background that varies with direction).
    ``poses`` (K, 4, 4) T_world_cam at ``times`` (K,) int64 (``motion_sample_times``; the pose
    track's knots among them).  The bound per interval is :func:`image_travel`'s for one object
    that does not move: the largest move of a box corner in the camera frame over the smallest
    distance to the box, or (``infinity``) the camera's rotation angle, whichever is larger."""
    lo, hi = np.asarray(box, np.float64).reshape(2, 3)
    corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), axis=-1).reshape(8, 3)
    poses = np.asarray(poses, np.float64)
    Rc, c = poses[:, :3, :3], poses[:, :3, 3]
    pc = np.einsum("tkj,tji->tki", corners[None] - c[:, None, :], Rc)         # (K, 8, 3) camera frame
    # the camera's distance to the box itself (0 inside): no point of it is nearer (its bounding
    # sphere's, the looser bound, gave a camera passing beside a long box a travel of pi)
    near = np.linalg.norm(np.maximum(np.maximum(lo - c, c - hi), 0.0), axis=1)
    move = np.linalg.norm(pc[1:] - pc[:-1], axis=2).max(axis=1)
    nearest = np.minimum(near[1:], near[:-1])
    with np.errstate(divide="ignore", invalid="ignore"):
        ang = np.where(move == 0, 0.0, np.where(nearest > move, move / np.maximum(nearest - move, 1e-300),
                                                math.pi))
    trace = np.einsum("tij,tij->t", Rc[:-1], Rc[1:])                          # trace(R_a^T R_b)
    cam_rot = np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)) if infinity else 0.0
    steps = np.maximum(np.minimum(ang, math.pi), cam_rot) * _magnification(camera)
    # without a background at infinity only the box can change pixels: the bounding box of its
    # corners' projections holds its image (a box wholly in front of the camera projects to a
    # convex set); a corner at or behind the image plane leaves it unbounded
    boxes = None
    if not infinity:
        z = pc[..., 2]
        u = camera.fx * pc[..., 0] / np.where(z > 0, z, 1.0) + camera.cx
        v = camera.fy * pc[..., 1] / np.where(z > 0, z, 1.0) + camera.cy
        boxes = np.stack([u.min(axis=1), v.min(axis=1), u.max(axis=1), v.max(axis=1)], axis=1)
        boxes[np.any(z <= 1e-9, axis=1)] = np.nan
    return ImageTravel(np.asarray(times, np.int64), np.concatenate([[0.0], np.cumsum(steps)]), boxes)


def _rotation_angle(R: np.ndarray) -> float:
    return float(math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0))))


def _magnification(camera) -> float:
    """Largest pixels per radian of direction change anywhere in the image."""
    dx = (max(camera.cx, camera.width - 1 - camera.cx) + 0.5) / camera.fx
    dy = (max(camera.cy, camera.height - 1 - camera.cy) + 0.5) / camera.fy
    return max(camera.fx, camera.fy) * (1.0 + dx * dx + dy * dy)
