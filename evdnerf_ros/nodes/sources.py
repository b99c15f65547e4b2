"""What the event publisher renders: a synthetic scene or a trained field, both behind
``source(T_world_cam, t_scene_ns) -> (H, W) linear intensity``.

Leave-out (``leave_out=True``): the synthetic renderer tests each primitive only against
the rays inside its projected bounding box (``SceneRenderer(prefilter=True)``); the field
renders only the rays that cross an occupied cell of the run's occupancy grid (or, without
a grid, the scene box) — every other pixel is the background, exactly what the full
render gives there. ``rays_rendered`` / ``rays_total`` count the saving: for the synthetic
scene in ray-primitive intersection tests (done / without leave-out: every ray against every
primitive), for the field in rays.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..geometry.camera import PinholeCamera


class SceneSource:
    kind = "scene"

    def __init__(self, scene, camera: PinholeCamera, *, supersample: int = 1, leave_out: bool = True):
        from ..sim.render import SceneRenderer
        from ..sim.scene import Scene, load_scene

        self.scene = scene if isinstance(scene, Scene) else load_scene(scene, check_cameras=False)
        self.camera = camera
        self.renderer = SceneRenderer(self.scene, camera, supersample, prefilter=leave_out)
        self.rays_total = 0

    @property
    def rays_rendered(self) -> int:
        return int(self.renderer.stats.tests)

    def __call__(self, T_world_cam, t_ns: int) -> np.ndarray:
        s = self.renderer.supersample
        self.rays_total += self.camera.width * self.camera.height * s * s * len(self.scene.leaves)
        return self.renderer(T_world_cam, int(t_ns))


class FieldSource:
    """A trained run (``evdnerf train`` output). Scene time [0, duration_ns] maps to the field's
    normalised time [0, 1] (clamped outside)."""

    kind = "field"

    def __init__(self, run_dir, camera: PinholeCamera, *, duration_ns: int, leave_out: bool = True,
                 chunk: int = 16384):
        import torch

        from ..eval.evaluate import load_field
        from ..field import OccupancyGrid
        from ..train.checkpoint import load_checkpoint
        from ..train.trainer import CHECKPOINT_NAME

        self.field, self.cfg, self.box, self.iteration, self.dynamic = load_field(run_dir)
        occ = load_checkpoint(f"{run_dir}/{CHECKPOINT_NAME}").get("extra", {}).get("occupied")
        self.occupancy = None
        if occ is not None:
            self.occupancy = OccupancyGrid(tuple(occ.shape))
            self.occupancy.occupied = occ.clone()
        if duration_ns <= 0:
            raise InputError(f"{run_dir}: field_duration must be > 0 s (the span the field's time 0..1 covers)")
        self.duration_ns = int(duration_ns)
        self.camera = camera
        self.leave_out = bool(leave_out)
        self.chunk = int(chunk)
        self.rays_total = 0
        self.rays_rendered = 0
        self._mask_cache = None
        self._torch = torch

    def _ray_mask(self, o, d, T):
        key = np.asarray(T, dtype=np.float64).tobytes()
        if self._mask_cache is not None and self._mask_cache[0] == key:   # a static camera: same rays
            return self._mask_cache[1]
        mask = self._compute_mask(o, d)
        self._mask_cache = (key, mask)
        return mask

    def _compute_mask(self, o, d):
        from ..field.render import normalize_points, ray_box_intersect, sample_along_rays

        t_near, t_far, hit = ray_box_intersect(o, d, self.box, self.cfg.near, self.cfg.far)
        if self.occupancy is None or not bool(hit.any()):
            return hit
        idx = self._torch.nonzero(hit).squeeze(1)
        z, _ = sample_along_rays(t_near[idx], t_far[idx], self.cfg.n_samples)
        pts = o[idx, None, :] + d[idx, None, :] * z[..., None]
        occ = self.occupancy.query(normalize_points(pts.reshape(-1, 3), self.box)).reshape(idx.numel(), -1)
        hit[idx] = occ.any(dim=1)
        return hit

    def __call__(self, T_world_cam, t_ns: int) -> np.ndarray:
        from ..field.render import camera_rays, render_rays

        torch = self._torch
        cam = self.camera
        tn = float(np.clip(int(t_ns) / self.duration_ns, 0.0, 1.0))
        with torch.no_grad():
            o, d = camera_rays(cam, T_world_cam)
            n = o.shape[0]
            idx = (torch.nonzero(self._ray_mask(o, d, T_world_cam)).squeeze(1) if self.leave_out
                   else torch.arange(n))
            out = torch.full((n,), float(self.cfg.background))
            for s in range(0, idx.numel(), self.chunk):
                j = idx[s:s + self.chunk]
                r = render_rays(self.field, o[j], d[j], tn, self.box, self.cfg.n_samples, near=self.cfg.near,
                                far=self.cfg.far, background=self.cfg.background, occupancy=self.occupancy)
                out[j] = r["grey"].float()
        self.rays_total += n
        self.rays_rendered += int(idx.numel())
        img = out.reshape(cam.height, cam.width).numpy().astype(np.float32)
        return np.maximum(img, 0.0)
