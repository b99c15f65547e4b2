"""A :class:`~evdnerf_ros.field.baked.BakedField`'s single-pixel rays on the CPU, compiled.

The publisher's per-pixel sampling asks for a few to a few thousand single pixels per call, each
from its own pose and time (``FieldRenderer.render_pixels``). A baked field needs no PyTorch at
all there: its samples are placed as every field's are (``ray_samples.SamplePlacer``: the tensor
path's float32 points and cell tests, only the kept ones), looked up and composited here in one compiled
pass (the trilinear lookups of the two baked frames around each ray's time blended linearly, as
``BakedField.decode``; the static grid outside the region, as ``decode_static``; a flat world's
fade at the region's boundary, as ``DynamicRegion.inner_weight``; ``ray_samples.accumulate``). The values agree with the tensor path to float rounding.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from .ray_samples import SamplePlacer, accumulate

#: Cache the machine code next to this module (numba falls back to its user cache folder).
_JIT = dict(cache=True, nogil=True, parallel=True)


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
def _render(x, is_dyn, counts, delta, which, times, backdrop, flat, fade_vol, static, frames, flo, fhi, out):
    """Each ray r's grey: its kept points ``x[r, :counts[r]]`` (box-normalised,
    ``SamplePlacer.slots``) looked up in the baked field at its time ``times[which[r]]`` and
    composited in order."""
    n_frames = frames.shape[0]
    for r in prange(backdrop.shape[0]):
        u = min(max(float(times[which[r]]), 0.0), 1.0) * (n_frames - 1)
        f0 = min(int(u), n_frames - 2)
        ft = u - f0
        a, b = frames[f0], frames[f0 + 1]
        transmit, acc, g = 1.0, 0.0, 0.0
        for s in range(counts[r]):
            x0, x1, x2 = float(x[r, s, 0]), float(x[r, s, 1]), float(x[r, s, 2])
            if is_dyn[r, s]:                        # the two frames around the ray's time (BakedField.decode)
                i, fi = _corner((x0 - flo[0]) / (fhi[0] - flo[0]) * (frames.shape[2] - 1), frames.shape[2])
                j, fj = _corner((x1 - flo[1]) / (fhi[1] - flo[1]) * (frames.shape[3] - 1), frames.shape[3])
                k, fk = _corner((x2 - flo[2]) / (fhi[2] - flo[2]) * (frames.shape[4] - 1), frames.shape[4])
                sigma = _trilinear(a, 0, i, j, k, fi, fj, fk) * (1 - ft) + _trilinear(b, 0, i, j, k, fi, fj, fk) * ft
                grey = _trilinear(a, 1, i, j, k, fi, fj, fk) * (1 - ft) + _trilinear(b, 1, i, j, k, fi, fj, fk) * ft
                if flat:
                    sigma *= _fade(fade_vol, x0, x1, x2)
            else:                                # the static grid (BakedField.decode_static)
                i, fi = _corner((x0 + 1.0) * 0.5 * (static.shape[1] - 1), static.shape[1])
                j, fj = _corner((x1 + 1.0) * 0.5 * (static.shape[2] - 1), static.shape[2])
                k, fk = _corner((x2 + 1.0) * 0.5 * (static.shape[3] - 1), static.shape[3])
                sigma = _trilinear(static, 0, i, j, k, fi, fj, fk)
                grey = _trilinear(static, 1, i, j, k, fi, fj, fk)
            transmit, acc, g = accumulate(transmit, acc, g, sigma, grey, delta[r])
        out[r] = g + (1.0 - acc) * backdrop[r]


class BakedMarcher:
    """The compiled single-pixel renderer of a baked ``field`` for one renderer's set-up: the
    ``SamplePlacer`` arguments (box, near / far, bins, the cells' box, occupancy and dynamic grids,
    a flat world). Its arrays are made once; each call renders a batch of rays."""

    def __init__(self, field, *, box, near: float, far: float, n_samples: int, cells_box, occupancy, dynamic,
                 flat: bool):
        self.placer = SamplePlacer(box=box, near=near, far=far, n_samples=n_samples, cells_box=cells_box,
                                   occupancy=occupancy, dynamic=dynamic, flat=flat)
        self.flat = bool(flat)
        self.fade = self.placer.dyn.astype(np.float32)[None] if flat else np.zeros((1, 1, 1, 1), np.float32)
        self.static = field.static.detach().cpu().numpy()
        self.frames = field.frames.detach().cpu().numpy()
        self.frame_lo = field.frame_lo.detach().cpu().numpy().astype(np.float64)
        self.frame_hi = field.frame_hi.detach().cpu().numpy().astype(np.float64)

    def warm_up(self) -> None:
        """Load the compiled passes (or compile them, once per machine) with a batch of no rays."""
        self(np.eye(4)[None], np.zeros(1), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))

    def __call__(self, poses, times, which, cam_dirs, backdrop, *, threads: int = 1):
        """(values (M,) float64 linear intensity, samples kept per ray (M,)) of M rays: ray i leaves
        pose ``poses[which[i]]`` ((K, 4, 4) T_world_cam) along camera-frame direction ``cam_dirs[i]``
        at normalised time ``times[which[i]]`` and sees ``backdrop[i]`` beyond the box."""
        x, dyn, counts, delta = self.placer.slots(poses, which, cam_dirs, threads=threads)
        m = counts.shape[0]
        out = np.empty(m, np.float64)
        _render(x, dyn, counts, delta, np.ascontiguousarray(which, np.int64), np.ascontiguousarray(times, np.float64),
                np.ascontiguousarray(np.broadcast_to(np.asarray(backdrop, np.float64), (m,))), self.flat, self.fade,
                self.static, self.frames, self.frame_lo, self.frame_hi, out)
        return out, counts


__all__ = ["BakedMarcher"]
