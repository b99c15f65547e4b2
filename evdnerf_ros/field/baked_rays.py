"""Rays through a :class:`~evdnerf_ros.field.baked.BakedField` in one compiled pass (CPU).

The publisher's per-pixel sampler asks for a few to a few thousand single pixels per call, each
from its own pose and time (``FieldRenderer.render_pixels``).  Through PyTorch every call costs
~100 small tensor operations whatever its size; here each ray is marched in one numba loop:
the same samples (``render.sample_along_rays``' bin centres of the box-clipped ray), the same
occupancy and dynamic-region tests (nearest cell), the same fade of a flat world's region
(``DynamicRegion.inner_weight``), the same trilinear lookups of the baked grids blended between
two frames (``BakedField.decode`` / ``decode_static``) and the same compositing
(``renderer._composite``), in float64 where PyTorch works in float32: the values agree to
float32 rounding, except where that rounding moves a sample across a cell face.

Only the samples that can fall in the box around the cells a ray must reach are visited (as
``FieldRenderer._sample_window``): the others have no density.  The ray loop runs on numba's
threads (``prange``), as many as torch uses.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

#: Cache the machine code next to this module (numba falls back to its user cache folder).
_JIT = dict(cache=True, nogil=True, parallel=True)


@numba.njit(inline="always")
def _slab(ox, oy, oz, dx, dy, dz, lo, hi, near, far):
    """(t_enter, t_exit) of a ray through an axis-aligned box, clipped to [near, far]; t_exit <=
    t_enter for a miss (``render.ray_box_intersect``)."""
    t_enter, t_exit = -np.inf, np.inf
    for a in range(3):
        o = ox if a == 0 else (oy if a == 1 else oz)
        d = dx if a == 0 else (dy if a == 1 else dz)
        if abs(d) < 1e-12:
            d = -1e-12 if d < 0 else 1e-12
        t0 = (lo[a] - o) / d
        t1 = (hi[a] - o) / d
        t_enter = max(t_enter, min(t0, t1))
        t_exit = min(t_exit, max(t0, t1))
    return max(t_enter, near), min(t_exit, far)


@numba.njit(inline="always")
def _cell(grid, x0, x1, x2):
    """Nearest cell of a boolean grid spanning [-1, 1]^3 (``occupancy.grid_lookup``)."""
    i = min(max(int((x0 + 1.0) * 0.5 * grid.shape[0]), 0), grid.shape[0] - 1)
    j = min(max(int((x1 + 1.0) * 0.5 * grid.shape[1]), 0), grid.shape[1] - 1)
    k = min(max(int((x2 + 1.0) * 0.5 * grid.shape[2]), 0), grid.shape[2] - 1)
    return grid[i, j, k]


@numba.njit(inline="always")
def _corner(u, n):
    """Lower vertex index and weight of grid coordinate ``u`` (in vertex units, clamped)."""
    u = min(max(u, 0.0), n - 1.0)
    i = min(int(u), max(n - 2, 0))
    return i, u - i


@numba.njit(inline="always")
def _trilinear(g, c, i, j, k, fi, fj, fk):
    """Trilinear value of channel ``c`` of a (C, X, Y, Z) grid from the lower corner (i, j, k)."""
    i1, j1, k1 = min(i + 1, g.shape[1] - 1), min(j + 1, g.shape[2] - 1), min(k + 1, g.shape[3] - 1)
    a = (g[c, i, j, k] * (1 - fk) + g[c, i, j, k1] * fk) * (1 - fj) + \
        (g[c, i, j1, k] * (1 - fk) + g[c, i, j1, k1] * fk) * fj
    b = (g[c, i1, j, k] * (1 - fk) + g[c, i1, j, k1] * fk) * (1 - fj) + \
        (g[c, i1, j1, k] * (1 - fk) + g[c, i1, j1, k1] * fk) * fj
    return a * (1 - fi) + b * fi


@numba.njit(inline="always")
def _fade(vol, x0, x1, x2):
    """``DynamicRegion.inner_weight``: twice the mask's trilinear value between cell centres
    (align_corners False, border), less one, clamped to [0, 1]."""
    i, fi = _corner(((x0 + 1.0) * vol.shape[1] - 1.0) * 0.5, vol.shape[1])
    j, fj = _corner(((x1 + 1.0) * vol.shape[2] - 1.0) * 0.5, vol.shape[2])
    k, fk = _corner(((x2 + 1.0) * vol.shape[3] - 1.0) * 0.5, vol.shape[3])
    return min(max(2.0 * _trilinear(vol, 0, i, j, k, fi, fj, fk) - 1.0, 0.0), 1.0)


@numba.njit(**_JIT)
def _march(poses, t, which, cam_dirs, backdrop, box_lo, box_hi, near, far, n_samples, cells_lo, cells_hi, occ,
           use_occ, dyn, fade_vol, flat, static, frames, flo, fhi, out, hits, evaluated):
    n_frames = frames.shape[0]
    for r in prange(which.shape[0]):
        out[r] = backdrop[r]
        hits[r] = False
        evaluated[r] = 0
        # the ray of camera direction cam_dirs[r] from pose which[r] (``render.pixel_rays``)
        P, c = poses[which[r]], cam_dirs[r]
        dx = P[0, 0] * c[0] + P[0, 1] * c[1] + P[0, 2] * c[2]
        dy = P[1, 0] * c[0] + P[1, 1] * c[1] + P[1, 2] * c[2]
        dz = P[2, 0] * c[0] + P[2, 1] * c[1] + P[2, 2] * c[2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        dx, dy, dz = dx / norm, dy / norm, dz / norm
        ox, oy, oz = P[0, 3], P[1, 3], P[2, 3]
        t_near, t_far = _slab(ox, oy, oz, dx, dy, dz, box_lo, box_hi, near, far)
        if not t_far > t_near:
            continue
        hits[r] = True
        delta = (t_far - t_near) / n_samples
        # only the samples that can fall in the cells' box (one more each side for rounding)
        ta, tb = _slab(ox, oy, oz, dx, dy, dz, cells_lo, cells_hi, near, far)
        if not tb > ta:
            continue
        k_lo = max(int(math.floor((ta - t_near) / delta - 0.5)) - 1, 0)
        k_hi = min(int(math.ceil((tb - t_near) / delta - 0.5)) + 1, n_samples - 1)
        u = min(max(t[which[r]], 0.0), 1.0) * (n_frames - 1)
        f0 = min(int(u), n_frames - 2)
        ft = u - f0
        transmit, grey, acc = 1.0, 0.0, 0.0
        for s in range(k_lo, k_hi + 1):
            z = t_near + (s + 0.5) * delta
            x0 = min(max(((ox + dx * z) - box_lo[0]) / (box_hi[0] - box_lo[0]) * 2.0 - 1.0, -1.0), 1.0)
            x1 = min(max(((oy + dy * z) - box_lo[1]) / (box_hi[1] - box_lo[1]) * 2.0 - 1.0, -1.0), 1.0)
            x2 = min(max(((oz + dz * z) - box_lo[2]) / (box_hi[2] - box_lo[2]) * 2.0 - 1.0, -1.0), 1.0)
            if use_occ and not _cell(occ, x0, x1, x2):
                continue
            if _cell(dyn, x0, x1, x2):
                # the baked frames at the ray's time (BakedField.decode)
                i, fi = _corner((x0 - flo[0]) / (fhi[0] - flo[0]) * (frames.shape[2] - 1), frames.shape[2])
                j, fj = _corner((x1 - flo[1]) / (fhi[1] - flo[1]) * (frames.shape[3] - 1), frames.shape[3])
                k, fk = _corner((x2 - flo[2]) / (fhi[2] - flo[2]) * (frames.shape[4] - 1), frames.shape[4])
                a, b = frames[f0], frames[f0 + 1]
                sigma = _trilinear(a, 0, i, j, k, fi, fj, fk) * (1 - ft) + _trilinear(b, 0, i, j, k, fi, fj, fk) * ft
                g = _trilinear(a, 1, i, j, k, fi, fj, fk) * (1 - ft) + _trilinear(b, 1, i, j, k, fi, fj, fk) * ft
                if flat:
                    sigma *= _fade(fade_vol, x0, x1, x2)
            elif flat:
                continue                          # a flat world: nothing outside the region
            else:                                 # the static grid (BakedField.decode_static)
                i, fi = _corner((x0 + 1.0) * 0.5 * (static.shape[1] - 1), static.shape[1])
                j, fj = _corner((x1 + 1.0) * 0.5 * (static.shape[2] - 1), static.shape[2])
                k, fk = _corner((x2 + 1.0) * 0.5 * (static.shape[3] - 1), static.shape[3])
                sigma = _trilinear(static, 0, i, j, k, fi, fj, fk)
                g = _trilinear(static, 1, i, j, k, fi, fj, fk)
            evaluated[r] += 1
            tau = sigma * delta
            w = -math.expm1(-tau) * transmit
            transmit *= math.exp(-tau)
            acc += w
            grey += w * g
        out[r] = grey + (1.0 - acc) * backdrop[r]


class BakedMarcher:
    """The compiled marcher of one renderer's set-up (module docstring): the baked ``field`` inside
    ``box`` with ``n_samples`` bins per ray between ``near`` and ``far``; ``cells_box``: (2, 3) world
    box of the cells a ray must reach (None: all of the box); ``occupancy`` / ``dynamic``: boolean
    (X, Y, Z) grids over the box or None; ``flat``: nothing outside ``dynamic``, whose density fades at
    its boundary. Its arrays are made once; each call marches a batch of rays."""

    def __init__(self, field, *, box, near: float, far: float, n_samples: int, cells_box, occupancy, dynamic,
                 flat: bool):
        f64 = np.float64
        self.box = np.asarray(box, f64).reshape(2, 3)
        self.cells = self.box if cells_box is None else np.asarray(cells_box, f64).reshape(2, 3)
        self.near, self.far, self.n_samples, self.flat = float(near), float(far), int(n_samples), bool(flat)
        self.use_occ = occupancy is not None
        self.occ = np.zeros((1, 1, 1), np.bool_) if occupancy is None else np.ascontiguousarray(occupancy, np.bool_)
        # no region: every sample is dynamic (``FieldRenderer._classify``)
        self.dyn = np.ones((1, 1, 1), np.bool_) if dynamic is None else np.ascontiguousarray(dynamic, np.bool_)
        self.fade = self.dyn.astype(np.float32)[None] if flat else np.zeros((1, 1, 1, 1), np.float32)
        self.static = field.static.detach().cpu().numpy()
        self.frames = field.frames.detach().cpu().numpy()
        self.frame_lo = field.frame_lo.detach().cpu().numpy().astype(f64)
        self.frame_hi = field.frame_hi.detach().cpu().numpy().astype(f64)

    def __call__(self, poses, times, which, cam_dirs, backdrop, *, threads: int = 1):
        """(values (M,) float64 linear intensity, rays that hit the box, rays with a sample
        evaluated, samples evaluated) of M rays: ray i leaves pose ``poses[which[i]]`` ((K, 4, 4)
        T_world_cam) along camera-frame direction ``cam_dirs[i]`` at normalised time
        ``times[which[i]]`` and sees ``backdrop[i]`` beyond the box."""
        f64 = np.float64
        m = int(np.asarray(which).shape[0])
        out, hits, evaluated = np.empty(m, f64), np.empty(m, np.bool_), np.empty(m, np.int64)
        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
        _march(np.ascontiguousarray(poses, f64), np.ascontiguousarray(times, f64),
               np.ascontiguousarray(which, np.int64), np.ascontiguousarray(cam_dirs, f64),
               np.ascontiguousarray(np.broadcast_to(np.asarray(backdrop, f64), (m,))), self.box[0], self.box[1],
               self.near, self.far, self.n_samples, self.cells[0], self.cells[1], self.occ, self.use_occ, self.dyn,
               self.fade, self.flat, self.static, self.frames, self.frame_lo, self.frame_hi, out, hits, evaluated)
        return out, int(hits.sum()), int(np.count_nonzero(evaluated)), int(evaluated.sum())


__all__ = ["BakedMarcher"]
