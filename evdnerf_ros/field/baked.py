"""A trained field baked into an explicit grid for playback (the publisher's ``bake`` switch).

``BakedField.bake(field, resolution=R, times=Tb, dynamic=region)`` evaluates the field once:

- a *static* grid: density and grey of the static field (``decode_static``) at the R^3
  vertices of the scene box (vertex i of an axis at ``-1 + 2 i / (R - 1)`` in box-normalised
  coordinates);
- *frames*: density and grey of the field as it was trained (static outside the dynamic
  region, time-dependent inside) at Tb evenly spaced normalised times ``k / (Tb - 1)``, on
  vertices of the same spacing covering only the dynamic region's bounding box (one voxel of
  margin; the whole box without a region).

Playback (the :class:`~evdnerf_ros.field.base.DynamicField` interface, so every renderer
plays it unchanged): ``decode_static`` is a trilinear lookup of the static grid; ``decode``
at time t is the trilinear lookup of the two frames around t, blended linearly in t.  It is an
approximation (density and grey interpolated between vertices and frames, where the field
would interpolate features and then decode): its error against the field is what the publish
benchmark puts on its error-against-run-time curve.  One lookup of 2 channels replaces the
field's plane lookups and MLP.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from .base import DynamicField


def _vertices(lo, hi, counts, device):
    """(prod(counts), 3) vertex coordinates, x slowest (C order of a (cx, cy, cz) grid)."""
    axes = [torch.linspace(float(lo[i]), float(hi[i]), int(counts[i]), device=device) for i in range(3)]
    g = torch.meshgrid(*axes, indexing="ij")
    return torch.stack(g, dim=-1).reshape(-1, 3)


def _lookup(grid: torch.Tensor, x: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Trilinear values (N, C) of a (C, X, Y, Z) vertex grid spanning [lo, hi] at (N, 3) points."""
    u = ((x - lo) / (hi - lo) * 2.0 - 1.0).clamp(-1.0, 1.0)
    coords = u[:, [2, 1, 0]].reshape(1, -1, 1, 1, 3)          # grid_sample: (x->W, y->H, z->D)
    out = F.grid_sample(grid[None], coords, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(grid.shape[0], -1).t()


class BakedField(DynamicField):
    """Density and grey on explicit grids, played back by interpolation (module docstring)."""

    reuses_space_features = False

    def __init__(self, static: torch.Tensor, frames: torch.Tensor, frame_lo, frame_hi):
        super().__init__()
        if static.dim() != 4 or static.shape[0] != 2 or frames.dim() != 5 or frames.shape[1] != 2 \
                or frames.shape[0] < 2:
            raise ValueError(f"baked grids must be (2, X, Y, Z) and (Tb >= 2, 2, X, Y, Z); got "
                             f"{tuple(static.shape)} and {tuple(frames.shape)}")
        self.register_buffer("static", static.float().contiguous())
        self.register_buffer("frames", frames.float().contiguous())
        self.register_buffer("frame_lo", torch.as_tensor(frame_lo, dtype=torch.float32))
        self.register_buffer("frame_hi", torch.as_tensor(frame_hi, dtype=torch.float32))
        self.register_buffer("box_lo", -torch.ones(3))
        self.register_buffer("box_hi", torch.ones(3))

    @property
    def n_times(self) -> int:
        return int(self.frames.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.static.numel() + self.frames.numel()) * 4

    @classmethod
    @torch.no_grad()
    def bake(cls, field, *, resolution: int = 64, times: int = 0, dynamic=None, keep_static: bool = True,
             chunk: int = 65536, device=None) -> "BakedField":
        """Bake ``field`` (module docstring). ``times`` 0: four frames per time texel of a
        ``planes`` field (``4 (time_resolution - 1) + 1``), else 65. ``keep_static`` False leaves the
        static grid out (a flat static world never reads it; ~30 % of the bake): ``decode_static``
        then refuses."""
        from ..device import module_device

        r = int(resolution)
        if r < 2:
            raise ValueError(f"bake resolution must be >= 2 vertices per axis, got {resolution}")
        tb = int(times) or (4 * (int(field.time_resolution) - 1) + 1 if hasattr(field, "time_resolution") else 65)
        if tb < 2:
            raise ValueError(f"bake times must be >= 2 frames, got {times}")
        dev = module_device(field) if device is None else device
        lo, hi = -np.ones(3), np.ones(3)
        flo, fhi = lo.copy(), hi.copy()
        mask = None
        if dynamic is not None:
            mask = dynamic.mask.to(dev)
            idx = torch.nonzero(mask)
            if idx.numel():
                res = np.asarray(mask.shape, np.float64)
                flo = np.maximum(-1.0, (idx.min(0).values.cpu().numpy() - 1) / res * 2 - 1)
                fhi = np.minimum(1.0, (idx.max(0).values.cpu().numpy() + 2) / res * 2 - 1)
            else:
                fhi = flo + 2.0 / (r - 1)      # nothing moves: a token frame grid (never looked up)
        step = 2.0 / (r - 1)
        fcounts = [max(2, int(math.ceil((fhi[i] - flo[i]) / step - 1e-9)) + 1) for i in range(3)]
        rs = r if keep_static else 1                 # left out: one token vertex, never read
        static = torch.zeros(2, rs ** 3, device=dev)
        if rs > 1:
            xs = _vertices(lo, hi, (rs, rs, rs), dev)
            for s in range(0, xs.shape[0], chunk):
                dens, grey = field.decode_static(field.space_features(xs[s:s + chunk]))
                static[0, s:s + chunk], static[1, s:s + chunk] = dens.float(), grey.float()
        xf = _vertices(flo, fhi, fcounts, dev)
        frames = torch.empty(tb, 2, xf.shape[0], device=dev)
        for s in range(0, xf.shape[0], chunk):
            xc = xf[s:s + chunk]
            dyn = None if mask is None else _grid_query(mask, xc)
            cols = [torch.full((xc.shape[0], 1), k / (tb - 1), device=dev) for k in range(tb)]
            for k, (dens, grey) in enumerate(field.evaluate_times(xc, cols, dyn)):
                frames[k, 0, s:s + chunk], frames[k, 1, s:s + chunk] = dens.float(), grey.float()
        out = cls(static.reshape(2, rs, rs, rs), frames.reshape(tb, 2, *fcounts), flo, fhi)
        if getattr(field, "background_map", None) is not None:
            out.background_map = field.background_map     # the same backdrop, not baked
        return out.to(dev)

    # ----- the field interface
    def space_features(self, x: torch.Tensor):
        return x.to(torch.float32)

    def decode_static(self, features):
        if self.static.shape[1] < 2:
            raise RuntimeError("this baked field was baked without its static grid (for a flat static world); "
                               "bake it with keep_static=True to render the static world")
        v = _lookup(self.static, features, self.box_lo, self.box_hi)
        return v[:, 0], v[:, 1]

    def decode(self, features, t: torch.Tensor):
        x = features
        n = x.shape[0]
        t = t.to(torch.float32).reshape(-1, 1).expand(n, 1)[:, 0]
        u = t.clamp(0.0, 1.0) * (self.n_times - 1)
        i0 = u.floor().clamp(max=self.n_times - 2).long()
        f = (u - i0.float())[:, None]
        if n and bool((i0 == i0[0]).all()):          # one time for every point: the publisher's case
            k = int(i0[0])
            v0 = _lookup(self.frames[k], x, self.frame_lo, self.frame_hi)
            v1 = _lookup(self.frames[k + 1], x, self.frame_lo, self.frame_hi)
            v = v0 * (1.0 - f) + v1 * f
            return v[:, 0], v[:, 1]
        out = torch.empty(n, 2, device=x.device)
        for k in torch.unique(i0).tolist():          # one frame pair per distinct time (usually one)
            sel = i0 == k
            xs = x[sel]
            v0 = _lookup(self.frames[k], xs, self.frame_lo, self.frame_hi)
            v1 = _lookup(self.frames[k + 1], xs, self.frame_lo, self.frame_hi)
            fs = f[sel]
            out[sel] = v0 * (1.0 - fs) + v1 * fs
        return out[:, 0], out[:, 1]

    def decode_times(self, features, times) -> tuple[torch.Tensor, torch.Tensor]:
        """(K, N) density and grey of the same N points at K times (a static camera's batch):
        every frame any of the times needs looked up in one pass, each time then the same blend
        of its two frames as ``decode``."""
        x = features
        u = torch.as_tensor(np.asarray(times, np.float64), dtype=torch.float32, device=x.device)
        u = u.clamp(0.0, 1.0) * (self.n_times - 1)
        i0 = u.floor().clamp(max=self.n_times - 2).long()
        f = (u - i0.float())[:, None]
        needed = torch.unique(torch.cat([i0, i0 + 1]))
        grid = self.frames[needed].reshape(-1, *self.frames.shape[2:])          # (F * 2, X, Y, Z)
        v = _lookup(grid, x, self.frame_lo, self.frame_hi).t().reshape(len(needed), 2, -1)
        slot = torch.searchsorted(needed, i0)                                  # i0's frame among them
        out = v[slot] * (1.0 - f[:, :, None]) + v[slot + 1] * f[:, :, None]    # (K, 2, N)
        return out[:, 0], out[:, 1]

    def forward(self, x: torch.Tensor, t: torch.Tensor):
        return self.decode(self.space_features(x), t)


def _grid_query(mask: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    from .occupancy import grid_lookup

    return grid_lookup(mask, x)


__all__ = ["BakedField"]
