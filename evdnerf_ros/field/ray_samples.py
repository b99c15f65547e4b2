"""Single-pixel rays of a trained field on the CPU: the geometry compiled (samples placed, then
composited), the field in PyTorch in between (``FieldRenderer.render_pixels``, the publisher's
per-pixel sampling of a moving camera).

The tensor path places every sample of every traced ray in the box around the cells it must reach,
normalises it and looks it up in the occupancy grid and the dynamic region before it knows which
samples matter: per call ~100 tensor operations over (rays x samples) points, ~80 % of a moving
camera's render time on the fork's orbit (the field's own lookups and decoder: ~20 %). Here
``SamplePlacer`` makes each ray from its pose and pixel and walks its samples once, keeping only
those the field is evaluated at (occupied ones; with a flat static world, the dynamic ones) in a
slot per ray; the caller evaluates the field at them in one batch and ``composite`` sums each
ray's kept samples in order. Every operation the tensor path does in float32 is done here in
float32 in the same order (ray-box slabs, bin centres, points, normalisation, the nearest-cell
lookups), so the same samples are kept at the same points; the compositing sums in float64
(equal to float32 rounding).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

#: Cache the machine code next to this module (numba falls back to its user cache folder).
_JIT = dict(cache=True, nogil=True, parallel=True)
f32 = np.float32


@numba.njit(inline="always")
def _ray(P, c):
    """Origin and unit direction (float32) of camera-frame direction ``c`` from pose ``P``, as
    ``render.pixel_rays`` (rotated and normalised in float64, then float32)."""
    dx = P[0, 0] * c[0] + P[0, 1] * c[1] + P[0, 2] * c[2]
    dy = P[1, 0] * c[0] + P[1, 1] * c[1] + P[1, 2] * c[2]
    dz = P[2, 0] * c[0] + P[2, 1] * c[1] + P[2, 2] * c[2]
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    return (f32(P[0, 3]), f32(P[1, 3]), f32(P[2, 3]), f32(dx / n), f32(dy / n), f32(dz / n))


@numba.njit(inline="always")
def _slab32(o, d, lo, hi, near, far):
    """``render.ray_box_intersect`` in float32: (t_enter, t_exit, hit)."""
    t_enter = f32(-np.inf)
    t_exit = f32(np.inf)
    for a in range(3):
        da = d[a]
        if abs(da) < f32(1e-12):
            da = f32(-1e-12) if da < 0 else f32(1e-12)
        inv = f32(1.0) / da
        t0 = (lo[a] - o[a]) * inv
        t1 = (hi[a] - o[a]) * inv
        t_enter = max(t_enter, min(t0, t1))
        t_exit = min(t_exit, max(t0, t1))
    t_enter = max(t_enter, near)
    t_exit = min(t_exit, far)
    return t_enter, t_exit, t_exit > t_enter


@numba.njit(inline="always")
def _cell32(grid, x0, x1, x2):
    """``occupancy.grid_lookup`` in float32: the nearest cell (truncated, clamped)."""
    i = min(max(int((x0 + f32(1.0)) * f32(0.5) * f32(grid.shape[0])), 0), grid.shape[0] - 1)
    j = min(max(int((x1 + f32(1.0)) * f32(0.5) * f32(grid.shape[1])), 0), grid.shape[1] - 1)
    k = min(max(int((x2 + f32(1.0)) * f32(0.5) * f32(grid.shape[2])), 0), grid.shape[2] - 1)
    return grid[i, j, k]


@numba.njit(inline="always")
def _walk(r, poses, which, cam_dirs, lo, hi, near, far, n_samples, cells_lo, cells_hi, occ, use_occ, dyn, flat,
          x_out, is_dyn):
    """Walk ray r's samples; keep those the field is evaluated at (into ``x_out`` / ``is_dyn``, in
    order); returns (bin length, samples kept), (0, 0) for a ray that misses the box."""
    ox, oy, oz, dx, dy, dz = _ray(poses[which[r]], cam_dirs[r])
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    t_near, t_far, hit = _slab32(o, d, lo, hi, near, far)
    if not hit:
        return f32(0.0), 0
    delta = (t_far - t_near) / f32(n_samples)
    # only the samples that can fall in the cells' box (float64, one more each side for rounding)
    ta, tb, through = _slab32(o, d, cells_lo, cells_hi, near, far)
    if not through:
        return delta, 0
    k_lo = max(int(math.floor((float(ta) - float(t_near)) / float(delta) - 0.5)) - 1, 0)
    k_hi = min(int(math.ceil((float(tb) - float(t_near)) / float(delta) - 0.5)) + 1, n_samples - 1)
    kept = 0
    scale0, scale1, scale2 = hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]
    for k in range(k_lo, k_hi + 1):
        z = t_near + (f32(k) + f32(0.5)) * delta
        x0 = min(max(((ox + dx * z) - lo[0]) / scale0 * f32(2.0) - f32(1.0), f32(-1.0)), f32(1.0))
        x1 = min(max(((oy + dy * z) - lo[1]) / scale1 * f32(2.0) - f32(1.0), f32(-1.0)), f32(1.0))
        x2 = min(max(((oz + dz * z) - lo[2]) / scale2 * f32(2.0) - f32(1.0), f32(-1.0)), f32(1.0))
        if use_occ and not _cell32(occ, x0, x1, x2):
            continue
        dynamic = _cell32(dyn, x0, x1, x2)
        if flat and not dynamic:
            continue
        x_out[kept, 0], x_out[kept, 1], x_out[kept, 2] = x0, x1, x2
        is_dyn[kept] = dynamic
        kept += 1
    return delta, kept


@numba.njit(**_JIT)
def _place(poses, which, cam_dirs, lo, hi, near, far, n_samples, cells_lo, cells_hi, occ, use_occ, dyn, flat,
           delta, counts, x_slots, dyn_slots):
    for r in prange(which.shape[0]):
        delta[r], counts[r] = _walk(r, poses, which, cam_dirs, lo, hi, near, far, n_samples, cells_lo, cells_hi,
                                    occ, use_occ, dyn, flat, x_slots[r], dyn_slots[r])


@numba.njit(inline="always")
def accumulate(transmit, acc, g, sigma, grey, delta):
    """One sample of front-to-back compositing (``renderer._composite``'s rule): the ray's
    transmittance, opacity and grey so far, after a sample of density ``sigma`` and grey ``grey``
    over a bin of length ``delta``."""
    tau = float(sigma) * float(delta)
    w = -math.expm1(-tau) * transmit
    return transmit * math.exp(-tau), acc + w, g + w * float(grey)


@numba.njit(**_JIT)
def _composite(offsets, sigma, grey, delta, backdrop, out):
    for r in prange(backdrop.shape[0]):
        transmit, acc, g = 1.0, 0.0, 0.0
        for s in range(offsets[r], offsets[r + 1]):
            transmit, acc, g = accumulate(transmit, acc, g, sigma[s], grey[s], delta[r])
        out[r] = g + (1.0 - acc) * backdrop[r]


class RaySamples:
    """The samples of a batch of single-pixel rays the field is evaluated at (``SamplePlacer``)."""

    __slots__ = ("x", "is_dynamic", "ray", "offsets", "counts", "delta")

    def __init__(self, x, is_dynamic, ray, offsets, counts, delta):
        self.x = x                      # (N, 3) float32 box-normalised points, ray by ray, in order
        self.is_dynamic = is_dynamic    # (N,) bool: inside the dynamic region
        self.ray = ray                  # (N,) int64: the ray of each point
        self.offsets = offsets          # (M + 1,) int64: ray r's points are offsets[r]:offsets[r + 1]
        self.counts = counts            # (M,) int64: points per ray
        self.delta = delta              # (M,) float32 bin length of each ray (0: it misses the box)


class SamplePlacer:
    """Places single-pixel rays' samples for one renderer's set-up: the scene ``box`` (float64
    (2, 3), used in float32 as the tensor path does), ``n_samples`` bins per ray in [near, far], the
    world box of the cells a ray must reach (``cells_box``), the occupancy grid (None: every point
    in the box) and the dynamic region (None: every point is dynamic) as boolean (X, Y, Z) grids
    over the box; ``flat``: only dynamic points are kept."""

    def __init__(self, *, box, near: float, far: float, n_samples: int, cells_box, occupancy, dynamic, flat: bool):
        box = np.asarray(box, np.float64).reshape(2, 3)
        self.lo, self.hi = box[0].astype(f32), box[1].astype(f32)
        cells = box if cells_box is None else np.asarray(cells_box, np.float64).reshape(2, 3)
        self.cells_lo, self.cells_hi = cells[0].astype(f32), cells[1].astype(f32)
        self.near, self.far, self.n_samples, self.flat = f32(near), f32(far), int(n_samples), bool(flat)
        self.use_occ = occupancy is not None
        self.occ = np.zeros((1, 1, 1), np.bool_) if occupancy is None else np.ascontiguousarray(occupancy, np.bool_)
        self.dyn = np.ones((1, 1, 1), np.bool_) if dynamic is None else np.ascontiguousarray(dynamic, np.bool_)

    def warm_up(self) -> None:
        """Load the compiled passes (or compile them, once per machine) with a batch of no rays."""
        rs = self(np.eye(4)[None], np.zeros(0, np.int64), np.zeros((0, 3)))
        composite(rs, np.zeros(0, f32), np.zeros(0, f32), np.zeros(0))

    def slots(self, poses, which, cam_dirs, *, threads: int = 1):
        """The kept samples of each ray in a slot of its own, walked once: (points (M, n_samples, 3)
        float32, dynamic (M, n_samples) bool, counts (M,): ray r's points are points[r, :counts[r]],
        bin lengths (M,) float32). Ray i leaves pose ``poses[which[i]]`` ((K, 4, 4) T_world_cam)
        along camera-frame direction ``cam_dirs[i]``."""
        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
        which = np.ascontiguousarray(which, np.int64)
        m, s = which.shape[0], self.n_samples
        delta, counts = np.empty(m, f32), np.empty(m, np.int64)
        x, dyn = np.empty((m, s, 3), f32), np.empty((m, s), np.bool_)
        _place(np.ascontiguousarray(poses, np.float64), which, np.ascontiguousarray(cam_dirs, np.float64), self.lo,
               self.hi, self.near, self.far, s, self.cells_lo, self.cells_hi, self.occ, self.use_occ, self.dyn,
               self.flat, delta, counts, x, dyn)
        return x, dyn, counts, delta

    def __call__(self, poses, which, cam_dirs, *, threads: int = 1) -> RaySamples:
        """The kept samples packed ray by ray (``slots``, then only the filled slots)."""
        x, dyn, counts, delta = self.slots(poses, which, cam_dirs, threads=threads)
        filled = np.arange(self.n_samples)[None, :] < counts[:, None]
        offsets = np.zeros(counts.size + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        return RaySamples(x[filled], dyn[filled], np.repeat(np.arange(counts.size), counts), offsets, counts, delta)


def composite(samples: RaySamples, sigma, grey, backdrop, *, threads: int = 1) -> np.ndarray:
    """(M,) float64 grey of each ray from its points' density and grey ((N,) each, in
    ``samples``' order) and what it sees beyond the box (``backdrop``, (M,)):
    ``renderer._composite``'s rule over the kept points (the others have no density)."""
    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    m = samples.delta.shape[0]
    out = np.empty(m, np.float64)
    _composite(samples.offsets, np.ascontiguousarray(sigma, f32), np.ascontiguousarray(grey, f32), samples.delta,
               np.ascontiguousarray(np.broadcast_to(np.asarray(backdrop, np.float64), (m,))), out)
    return out


__all__ = ["RaySamples", "SamplePlacer", "accumulate", "composite"]
