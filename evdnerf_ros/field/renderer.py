"""A trained field as a :class:`evdnerf_ros.renderer.Renderer`: ``render(T_world_cam, t_ns)``
-> (H, W) float32 linear intensity, so the event generator, the time sampler and the event
publisher drive it exactly as they drive the synthetic scene renderer.

Time: scene time ``t_ns`` (int64) maps to the field's normalised time
``(t_ns - t_origin_ns) / duration_ns``, computed from the int64 difference and clamped to
[0, 1] (the field knows nothing outside the span it was trained on).

Leave-out (``leave_out=True``): only rays that cross an occupied cell of the occupancy grid
(or, without a grid, the scene box) are rendered; every other pixel is the background,
exactly what the full render gives there.  A static camera's ray mask is cached.
``rays_rendered`` / ``rays_total`` count the saving (rays rendered / rays of the images).
Build one from a run folder with :meth:`evdnerf_ros.train.run.TrainedRun.renderer`.
"""

from __future__ import annotations

import operator

import numpy as np
import torch

from ..errors import InputError
from ..renderer import CameraRenderer
from .render import (camera_rays, normalize_points, ray_box_intersect, render_rays,
                     sample_along_rays)


class FieldRenderer(CameraRenderer):
    """Renders a field (in eval mode) through ``camera`` inside ``box``."""

    kind = "field"

    def __init__(self, field, camera, box, *, duration_ns: int, t_origin_ns: int = 0,
                 n_samples: int = 64, near: float = 0.0, far: float = float("inf"),
                 background: float = 0.0, occupancy=None, leave_out: bool = True,
                 chunk: int = 16384, source: str = "trained field"):
        if isinstance(duration_ns, bool) or not isinstance(duration_ns, (int, np.integer)) \
                or duration_ns <= 0:
            raise InputError(f"{source}: the span the field's time 0..1 covers must be a positive "
                             f"whole number of nanoseconds, got {duration_ns!r}")
        if int(chunk) < 1:
            raise InputError(f"{source}: chunk must be >= 1 ray, got {chunk}")
        self.field = field
        self.camera = camera
        self.box = np.asarray(box, np.float64)
        self.duration_ns = int(duration_ns)
        self.t_origin_ns = int(t_origin_ns)
        self.n_samples = int(n_samples)
        self.near, self.far, self.background = float(near), float(far), float(background)
        self.occupancy = occupancy
        self.leave_out = bool(leave_out)
        self.chunk = int(chunk)
        self.source = source
        self.rays_total = 0
        self.rays_rendered = 0
        self._mask_cache = None

    def normalized_time(self, t_ns) -> float:
        """The field's time in [0, 1] of scene time ``t_ns`` (int64 ns)."""
        if isinstance(t_ns, (bool, float, np.floating)):
            raise InputError(f"{self.source}: render time must be int64 nanoseconds; got {t_ns!r}")
        try:
            t = operator.index(t_ns)
        except TypeError:
            raise InputError(f"{self.source}: render time must be int64 nanoseconds; "
                             f"got {t_ns!r}") from None
        return float(np.clip((t - self.t_origin_ns) / self.duration_ns, 0.0, 1.0))

    def _ray_mask(self, o, d, T):
        key = np.asarray(T, dtype=np.float64).tobytes()
        if self._mask_cache is not None and self._mask_cache[0] == key:   # a static camera: same rays
            return self._mask_cache[1]
        mask = self._compute_mask(o, d)
        self._mask_cache = (key, mask)
        return mask

    def _compute_mask(self, o, d):
        t_near, t_far, hit = ray_box_intersect(o, d, self.box, self.near, self.far)
        if self.occupancy is None or not bool(hit.any()):
            return hit
        idx = torch.nonzero(hit).squeeze(1)
        z, _ = sample_along_rays(t_near[idx], t_far[idx], self.n_samples)
        pts = o[idx, None, :] + d[idx, None, :] * z[..., None]
        occ = self.occupancy.query(normalize_points(pts.reshape(-1, 3), self.box)).reshape(idx.numel(), -1)
        hit[idx] = occ.any(dim=1)
        return hit

    def render(self, T_world_cam, t_ns) -> np.ndarray:
        """(H, W) float32 linear intensity (>= 0) at scene time ``t_ns`` (the Renderer interface)."""
        from ..geometry.poses import check_rigid

        tn = self.normalized_time(t_ns)
        T = check_rigid(T_world_cam, "T_world_cam")
        cam = self.camera
        with torch.no_grad():
            o, d = camera_rays(cam, T)
            n = o.shape[0]
            idx = (torch.nonzero(self._ray_mask(o, d, T)).squeeze(1) if self.leave_out
                   else torch.arange(n))
            out = torch.full((n,), self.background)
            for s in range(0, idx.numel(), self.chunk):
                j = idx[s:s + self.chunk]
                r = render_rays(self.field, o[j], d[j], tn, self.box, self.n_samples, near=self.near,
                                far=self.far, background=self.background, occupancy=self.occupancy)
                out[j] = r["grey"].float()
        self.rays_total += n
        self.rays_rendered += int(idx.numel())
        img = out.reshape(cam.height, cam.width).numpy().astype(np.float32)
        return np.maximum(img, 0.0)



__all__ = ["FieldRenderer"]
