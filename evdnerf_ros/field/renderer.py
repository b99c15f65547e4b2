"""A trained field as a :class:`evdnerf_ros.renderer.Renderer`: ``render(T_world_cam, t_ns)``
-> (H, W) float32 linear intensity, so the event generator, the time sampler and the event
publisher drive it exactly as they drive the synthetic scene renderer.

Time: scene time ``t_ns`` (int64) maps to the field's normalised time
``(t_ns - t_origin_ns) / duration_ns``, computed from the int64 difference and clamped to
[0, 1] (the field knows nothing outside the span it was trained on).

The field is rendered as it was trained and is evaluated: with the run's dynamic region
(``dynamic``), samples outside it take the static field (``DynamicField.decode_static``).

Work per image is split into a *plan* of the pose (rays, samples, occupancy, which samples
are dynamic, the static samples' density and grey, the dynamic samples' space features, and
the finished value of every ray that crosses no dynamic sample) and a *playback* at each
time (only the dynamic samples' time-dependent part, then compositing of the rays that
cross them).  The switches, each a pure saving (the images stay the same up to float
rounding of batched matrix products, ~1e-7; the tests hold them to 1e-6):

- ``leave_out``: trace only rays that cross an occupied cell of the occupancy grid (or,
  without a grid, the scene box); every other pixel is the background, exactly what the
  full render gives there.  Rays are first tested against the box around the cells they
  must reach (the occupied ones; with a flat static world, the dynamic region's), and of a
  traced ray only the samples that can fall in that box are placed, looked up and composited
  (the same points; the others have no density; a moving camera's plan 13 % faster on the fork).
- ``reuse_static``: keep the plan while the camera pose does not change (a static camera;
  poses equal within ``POSE_SAME`` = 1e-9, float rounding of an interpolated track):
  the static rays and samples are then evaluated once, and each new time costs only the
  dynamic samples.  A moving camera re-plans at every pose (no reuse possible; the plan is
  then what a plain render costs).
- a field with a learned background (``field.background_map``) gives each ray the grey of
  its direction where it leaves the box, computed with the plan (once per pose).
- a ``planes`` field plays each time back through ``PlanesField.decode_at`` (its time planes
  blended to the row at that time once, then read at each sample's precomputed columns; equal
  to ``decode`` up to float rounding).
- ``static_world``: what a ray sees outside the run's dynamic region. ``"field"`` (the
  default): the static field and the learned background, as trained and evaluated.
  ``"flat"``: nothing there (density 0) in front of one constant grey (the learned
  background's mean over the sphere, else ``background``), so only rays that cross the
  dynamic region are traced and no static sample is evaluated; inside the region the density
  fades to 0 at its boundary (``DynamicRegion.inner_weight``), so that a ray sweeping across a
  voxel face changes continuously instead of popping. Static training views say
  next to nothing about the static world (it makes no events in them): a moving camera
  sees the static field's fog and the background's noise sweep past as events the true
  scene does not have (4x the true events on the fork's orbit), and ``"flat"`` leaves them
  out; a static camera sees the static world make no events either way, but the moving
  parts' contrast against what was behind them in training needs ``"field"``.
- ``field`` may also be a :class:`~evdnerf_ros.field.baked.BakedField` (the ``bake``
  setting of :meth:`TrainedRun.renderer`): an explicit grid played back by interpolation, an
  approximation whose error the publish benchmark measures.

``render_pixels`` draws single pixels of many poses and times in one batch (the publisher's
per-pixel sampling, ``sim.sampling.simulate_pixels``): no plan is kept, each dynamic sample is
decoded at its ray's own time.  On the CPU (``compiled_rays``) its samples are placed in compiled
passes (``field.ray_samples``: the same float32 points and cell tests, ray by ray, only the kept
ones) and composited there, the field evaluated in between in one batch; a baked field is marched
whole (``field.baked_rays``).  Both give the tensor path's values to float rounding.

``rays_rendered`` / ``rays_total`` count rays traced (leave-out) / rays of the images, per call;
``samples_evaluated`` / ``samples_total`` count field evaluations done / what a full render of
every sample of every traced ray at every call would do.  ``device``: where every tensor
lives (``evdnerf_ros.device``); images come back as CPU numpy arrays.
Build one from a run folder with :meth:`evdnerf_ros.train.run.TrainedRun.renderer`.
"""

from __future__ import annotations

import operator

import numpy as np
import torch

from ..errors import InputError
from ..renderer import CameraRenderer
from .base import as_time_column
from .occupancy import cells_box
from .render import (area_rays, background_grey, finer, flat_background, normalize_points, pixel_means,
                     pixel_rays, ray_box_intersect, sample_along_rays, subpixels, volume_weights)

#: What a ray sees outside the dynamic region (module docstring).
STATIC_WORLDS = ("field", "flat")


def resolve_static_world(choice: str, *, moving: bool, has_region: bool) -> str:
    """``choice`` (auto, field or flat) for one camera: auto is flat for a moving camera of a
    run with a dynamic region, else field."""
    if choice != "auto":
        return choice
    return "flat" if moving and has_region else "field"
#: A static camera's plan is kept only while it holds at most this many bytes.
PLAN_CACHE_BYTES = 1 << 30
#: Poses whose matrices differ by at most this (m, or rotation entries) are the same pose: a
#: static camera's pose interpolated along a trajectory wobbles by float rounding (~1e-16).
POSE_SAME = 1e-9


class _ChunkPlan:
    """One chunk of rays of one pose: what does not depend on time (module docstring)."""

    __slots__ = ("static_rays", "static_grey", "dyn_rays", "dyn_background", "delta", "base_sigma",
                 "base_grey", "dyn_idx", "dyn_weight", "feats", "n_static_samples", "n_samples_traced", "n_rays", "width",
                 "nbytes")


def _feature_bytes(feats) -> int:
    if isinstance(feats, torch.Tensor):
        return feats.numel() * feats.element_size()
    if isinstance(feats, (list, tuple)):
        return sum(_feature_bytes(f) for f in feats)
    return 0


class FieldRenderer(CameraRenderer):
    """Renders a field (in eval mode) through ``camera`` inside ``box``."""

    kind = "field"

    def __init__(self, field, camera, box, *, duration_ns: int, t_origin_ns: int = 0,
                 n_samples: int = 64, near: float = 0.0, far: float = float("inf"),
                 background: float = 0.0, occupancy=None, dynamic=None, leave_out: bool = True,
                 reuse_static: bool = True, static_world: str = "field", chunk: int = 16384,
                 device=None, source: str = "trained field", pixel_samples: int = 1):
        """``pixel_samples``: each pixel the mean of that many sub-pixel rays per side (the run's
        ``TrainConfig.pixel_samples``)."""
        from ..device import module_device, resolve_device

        if isinstance(duration_ns, bool) or not isinstance(duration_ns, (int, np.integer)) \
                or duration_ns <= 0:
            raise InputError(f"{source}: the span the field's time 0..1 covers must be a positive "
                             f"whole number of nanoseconds, got {duration_ns!r}")
        if int(chunk) < 1:
            raise InputError(f"{source}: chunk must be >= 1 ray, got {chunk}")
        self.device = module_device(field) if device is None else resolve_device(device, f"{source}: device")
        self.field = field.to(self.device)
        self.camera = camera
        if not 1 <= int(pixel_samples) <= 8:
            raise InputError(f"{source}: pixel_samples must be 1..8 rays per pixel side, got {pixel_samples}")
        self.pixel_samples = int(pixel_samples)
        self.ray_camera = finer(camera, self.pixel_samples)      # whose pixels the rays go through
        self.box = np.asarray(box, np.float64)
        self.duration_ns = int(duration_ns)
        self.t_origin_ns = int(t_origin_ns)
        self.n_samples = int(n_samples)
        self.near, self.far, self.background = float(near), float(far), float(background)
        self.occupancy = _on_device(occupancy, "occupied", self.device)
        self.dynamic = _on_device(dynamic, "mask", self.device)
        self.leave_out = bool(leave_out)
        self.reuse_static = bool(reuse_static)
        if static_world not in STATIC_WORLDS:
            raise InputError(f"{source}: static_world must be one of {', '.join(STATIC_WORLDS)}, got {static_world!r}")
        if static_world == "flat" and self.dynamic is None:
            raise InputError(f"{source}: static_world 'flat' keeps only the run's dynamic region, and this run has "
                             "none (trained with dynamic_region: false); use static_world 'field'")
        self.static_world = static_world
        self.flat_grey = flat_background(self.field, self.background) if static_world == "flat" else None
        self.chunk = int(chunk)
        self.source = source
        self.rays_total = 0
        self.rays_rendered = 0
        self.samples_total = 0
        self.samples_evaluated = 0
        self._plan_cache = None
        self._cells_box_cache = None
        self._compiled = self._cam_dirs = None  # the compiled single-pixel pass, every pixel's camera-frame ray
        #: ``render_pixels`` on the CPU places its samples in compiled passes (``field.ray_samples``; a baked
        #: field marched whole, ``field.baked_rays``); False: the tensor path (what CUDA runs)
        self.compiled_rays = self.device.type == "cpu"

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

    def normalized_times(self, t_ns) -> np.ndarray:
        """(K,) float32 ``normalized_time`` of each of the scene times ``t_ns`` ((K,) int64 ns)."""
        t = np.asarray(t_ns).reshape(-1)
        if t.size and t.dtype.kind not in "iu":
            raise InputError(f"{self.source}: render times must be int64 nanoseconds; got an array of {t.dtype}")
        span = (t.astype(np.int64) - np.int64(self.t_origin_ns)) / float(self.duration_ns)
        return np.clip(span, 0.0, 1.0).astype(np.float32)

    # ------------------------------------------------------------------ plan
    def _plan(self, T) -> tuple[list[_ChunkPlan], torch.Tensor]:
        """The chunk plans of pose ``T`` and the image every pixel starts from: what each ray
        sees where it leaves the box (the background, constant or of the ray's direction)."""
        key = np.asarray(T, dtype=np.float64)
        if self.reuse_static and self._plan_cache is not None and \
                float(np.abs(self._plan_cache[0] - key).max()) <= POSE_SAME:
            return self._plan_cache[1:]
        o, d = area_rays(self.camera, T, self.pixel_samples, device=self.device)
        n = o.shape[0]
        backdrop, rays = self._backdrop_and_rays(o, d)
        plans = [p for p in (self._plan_chunk(o[j], d[j], j, backdrop[j]) for j in torch.split(rays, self.chunk))
                 if p.n_rays]
        if self.reuse_static and sum(p.nbytes for p in plans) + 4 * n <= PLAN_CACHE_BYTES:
            self._plan_cache = (key, plans, backdrop)
        else:
            self._plan_cache = None
        return plans, backdrop

    def _backdrop_and_rays(self, o, d):
        """What each ray sees where it leaves the box (the background, constant or of the ray's
        direction) and the indices of the rays to trace (``_skips_rays``)."""
        n = o.shape[0]
        grey = self.flat_grey if self.flat_grey is not None else background_grey(self.field, d, self.background)
        backdrop = torch.as_tensor(grey, dtype=torch.float32, device=self.device).expand(n).contiguous()
        rays = torch.arange(n, device=self.device)
        if self._skips_rays:
            rays = rays[self._may_see_cells(o, d)]
        return backdrop, rays

    @property
    def _skips_rays(self) -> bool:
        """Only rays with a sample in a cell that can show anything are traced (module docstring)."""
        return self.leave_out or self.flat_grey is not None

    def _cells_box(self) -> np.ndarray | None:
        """(2, 3) world box around every cell a traced ray must reach (``occupancy.cells_box``):
        the occupancy grid's occupied cells, with a flat static world within the dynamic
        region's; None when there is none."""
        lo, hi = self.box.reshape(2, 3)
        out = np.stack([lo, hi])
        grids = [self.occupancy.occupied] if self.occupancy is not None and self.occupancy.enabled else []
        if self.flat_grey is not None:
            grids.append(self.dynamic.mask)
        for g in grids:
            cells = cells_box(g, self.box)
            if cells is None:
                return None
            out = np.stack([np.maximum(out[0], cells[0]), np.minimum(out[1], cells[1])])
        return out if bool(np.all(out[1] > out[0])) else None

    def content_box(self) -> np.ndarray | None:
        """(2, 3) world box around everything this renderer can show but a background at infinity:
        with a flat static world the cells' box (None: nothing), else the scene box."""
        return self._cached_cells_box() if self.flat_grey is not None else self.box.reshape(2, 3)

    @property
    def shows_infinity(self) -> bool:
        """Whether what rays see beyond the box changes with their direction (a learned background
        map, unless the static world is flat)."""
        return self.flat_grey is None and getattr(self.field, "background_map", None) is not None

    def _may_see_cells(self, o, d):
        """(N,) bool: rays that hit the box and the cells' box (``_cells_box``); a cheap test
        before the exact one per sample in ``_plan_chunk``."""
        _, _, hit = ray_box_intersect(o, d, self.box, self.near, self.far)
        cells = self._cached_cells_box()
        if cells is None:
            return torch.zeros_like(hit)            # nothing to see: no ray is traced
        _, _, hit_cells = ray_box_intersect(o, d, cells, self.near, self.far)
        return hit & hit_cells

    def _classify(self, x, inside):
        """(valid, dynamic) of normalised sample points ``x`` (``inside``: within the box)."""
        valid = inside if self.occupancy is None else inside & self.occupancy.query(x)
        return valid, (valid if self.dynamic is None else valid & self.dynamic.query(x))

    def _sample_window(self, o, d, t_near, delta, hit):
        """(rays, W) indices of the samples of each ray that can fall in the cells' box
        (``_cells_box``; one sample wider each side for rounding), W < n_samples; None when that
        box does not narrow them (no grid, or a ray crossing it end to end)."""
        if not (self.occupancy is not None and self.occupancy.enabled) and self.flat_grey is None:
            return None
        cells = self._cached_cells_box()
        if cells is None or not o.shape[0]:
            return None
        S = self.n_samples
        ta, tb, hit_cells = ray_box_intersect(o, d, cells, self.near, self.far)
        through = hit & hit_cells
        step = torch.where(through, delta, torch.ones_like(delta))
        # sample k sits at t_near + (k + 0.5) * delta
        lo = torch.where(through, ((ta - t_near) / step - 0.5).floor() - 1, torch.zeros_like(ta)).clamp(0, S - 1)
        hi = torch.where(through, ((tb - t_near) / step - 0.5).ceil() + 1, torch.zeros_like(tb)).clamp(0, S - 1)
        w = int((hi - lo).max()) + 1
        if w >= S:
            return None
        start = torch.minimum(lo.long(), torch.full_like(lo, S - w, dtype=torch.long))
        return start[:, None] + torch.arange(w, device=o.device)[None, :]

    def _cached_cells_box(self):
        if self._cells_box_cache is None:
            self._cells_box_cache = (self._cells_box(),)
        return self._cells_box_cache[0]

    def _plan_chunk(self, o, d, rays, backdrop, playback: bool = True) -> _ChunkPlan:
        S, dev = self.n_samples, self.device
        t_near, t_far, hit = ray_box_intersect(o, d, self.box, self.near, self.far)
        z, delta = sample_along_rays(t_near, t_far, S)
        k = self._sample_window(o, d, t_near, delta, hit)
        if k is not None:
            # only the samples that can fall in the cells' box are placed, looked up and composited
            # (the same points): every other sample of the ray is neither occupied nor, flat,
            # dynamic, so it has no density and leaves the ray's sums as they are
            z = z.gather(1, k)
        W = z.shape[1]
        x = normalize_points((o[:, None, :] + d[:, None, :] * z[..., None]).reshape(-1, 3), self.box)
        valid, is_dyn = self._classify(x, hit[:, None].expand(-1, W).reshape(-1))
        if self._skips_rays:
            # trace only rays with a sample that can show anything: an occupied one (with a flat
            # static world, a dynamic one); every other ray sees exactly the backdrop
            seen = (is_dyn if self.flat_grey is not None else valid).reshape(-1, W).any(dim=1)
            if not bool(seen.all()):
                keep = torch.nonzero(seen).squeeze(1)
                rays, backdrop, delta = rays[keep], backdrop[keep], delta[keep]
                x, valid, is_dyn = (a.reshape(-1, W, *a.shape[1:])[keep].reshape(-1, *a.shape[1:])
                                    for a in (x, valid, is_dyn))
        m = rays.numel()
        # a flat static world: nothing outside the dynamic region, no static sample to evaluate
        s_idx = torch.nonzero(valid & ~is_dyn).squeeze(1) if self.flat_grey is None else x.new_zeros(0, dtype=torch.long)
        sigma = torch.zeros(m * W, dtype=torch.float32, device=dev)
        grey = torch.zeros_like(sigma)
        if s_idx.numel():
            dens, g = self.field.decode_static(self.field.space_features(x[s_idx]))
            sigma = sigma.index_put((s_idx,), dens.float())
            grey = grey.index_put((s_idx,), g.float())
        ray_dyn = is_dyn.reshape(m, W).any(dim=1)
        p = _ChunkPlan()
        p.n_static_samples = int(s_idx.numel())
        p.n_samples_traced = m * S        # what a full render of these rays evaluates
        p.width = W
        p.n_rays = m
        st = torch.nonzero(~ray_dyn).squeeze(1)
        p.static_rays = rays[st]
        p.static_grey = _composite(sigma.reshape(m, W)[st], grey.reshape(m, W)[st], delta[st], backdrop[st])
        dy = torch.nonzero(ray_dyn).squeeze(1)
        p.dyn_rays = rays[dy]
        p.dyn_background = backdrop[dy]
        p.delta = delta[dy]
        p.base_sigma = sigma.reshape(m, W)[dy].reshape(-1)
        p.base_grey = grey.reshape(m, W)[dy].reshape(-1)
        dmask = is_dyn.reshape(m, W)[dy].reshape(-1)
        p.dyn_idx = torch.nonzero(dmask).squeeze(1)
        xd = x.reshape(m, W, 3)[dy].reshape(-1, 3)[p.dyn_idx]
        p.feats = None
        p.dyn_weight = self.dynamic.inner_weight(xd) if self.flat_grey is not None and xd.shape[0] else None
        if p.dyn_idx.numel():
            p.feats = self.field.space_features(xd)
            if playback and hasattr(self.field, "playback_features"):     # planes: time rows read by gathers
                p.feats = self.field.playback_features(p.feats)
        p.nbytes = (_feature_bytes(p.feats) + 4 * (2 * p.base_sigma.numel() + 2 * p.delta.numel())
                    + 8 * (p.dyn_idx.numel() + p.dyn_rays.numel() + p.static_rays.numel()) + 4 * p.static_grey.numel())
        self.samples_evaluated += p.n_static_samples
        return p

    # ------------------------------------------------------------------ playback
    def render(self, T_world_cam, t_ns) -> np.ndarray:
        """(H, W) float32 linear intensity (>= 0) at scene time ``t_ns`` (the Renderer interface)."""
        return self._render_at(T_world_cam, [self.normalized_time(t_ns)])[0]

    def render_times(self, T_world_cam, t_ns) -> np.ndarray:
        """(K, H, W) float32: ``render`` at each of the K scene times ``t_ns`` from one pose, in one
        batch (each dynamic sample looked up at every time at once; on a GPU far fewer launches
        and one copy back instead of K).  The same images as K calls of ``render``."""
        return self._render_at(T_world_cam, [self.normalized_time(t) for t in np.asarray(t_ns).reshape(-1)])

    def _render_at(self, T_world_cam, tns) -> np.ndarray:
        """(K, H, W) images from one pose at the field's times ``tns``."""
        from ..geometry.poses import check_rigid

        T = check_rigid(T_world_cam, "T_world_cam")
        cam, s, k_times = self.camera, self.pixel_samples, len(tns)
        n = cam.width * cam.height * s * s
        with torch.no_grad():
            plans, backdrop = self._plan(T)
            out = backdrop[None].repeat(k_times, 1)
            for p in plans:
                self._play_times(p, out, tns)
        self.rays_total += n * k_times
        img = pixel_means(out.reshape(-1), s).reshape(k_times, cam.height, cam.width)
        return np.maximum(img.cpu().numpy().astype(np.float32), 0.0)

    def _decode_times(self, p: _ChunkPlan, tns) -> tuple[torch.Tensor, torch.Tensor]:
        """(K, n) density and grey of a chunk's dynamic samples at each time."""
        if hasattr(self.field, "decode_times"):
            return self.field.decode_times(p.feats, tns)
        pairs = [self.field.decode_at(p.feats, tn) if hasattr(self.field, "decode_at") else
                 self.field.decode(p.feats, as_time_column(tn, p.dyn_idx.numel(), self.device)) for tn in tns]
        return torch.stack([d for d, _ in pairs]), torch.stack([g for _, g in pairs])

    def _play_times(self, p: _ChunkPlan, out: torch.Tensor, tns) -> None:
        """``_play`` of one chunk at K times into the rows of ``out`` (K, rays)."""
        k_times = len(tns)
        self.samples_total += p.n_samples_traced * k_times
        self.rays_rendered += p.n_rays * k_times
        if p.static_rays.numel():
            out[:, p.static_rays] = p.static_grey
        if not p.dyn_rays.numel():
            return
        k = p.dyn_rays.numel()
        sigma = p.base_sigma.repeat(k_times, 1)
        grey = p.base_grey.repeat(k_times, 1)
        if p.dyn_idx.numel():
            dens, g = self._decode_times(p, tns)
            if p.dyn_weight is not None:
                dens = dens * p.dyn_weight
            sigma[:, p.dyn_idx] = dens.float()
            grey[:, p.dyn_idx] = g.float()
            self.samples_evaluated += int(p.dyn_idx.numel()) * k_times
        rows = _composite(sigma.reshape(k_times * k, -1), grey.reshape(k_times * k, -1),
                          p.delta.repeat(k_times), p.dyn_background.repeat(k_times))
        out[:, p.dyn_rays] = rows.reshape(k_times, k)

    def _play(self, p: _ChunkPlan, out: torch.Tensor, decode) -> None:
        """Write a chunk's rays into ``out``: the static rays' grey, and the dynamic rays composited
        with their dynamic samples' (density, grey) from ``decode(p)``."""
        self.samples_total += p.n_samples_traced
        self.rays_rendered += p.n_rays
        if p.static_rays.numel():
            out[p.static_rays] = p.static_grey
        if not p.dyn_rays.numel():
            return
        sigma, grey = p.base_sigma, p.base_grey
        if p.dyn_idx.numel():
            dens, g = decode(p)
            if p.dyn_weight is not None:
                dens = dens * p.dyn_weight
            sigma = sigma.index_put((p.dyn_idx,), dens.float())
            grey = grey.index_put((p.dyn_idx,), g.float())
            self.samples_evaluated += int(p.dyn_idx.numel())
        k = p.dyn_rays.numel()
        out[p.dyn_rays] = _composite(sigma.reshape(k, -1), grey.reshape(k, -1), p.delta, p.dyn_background)

    def render_pixels(self, poses, t_ns, which, pixels) -> np.ndarray:
        """(M,) float32 linear intensity (>= 0) of row-major pixel ``pixels[i]`` seen from pose
        ``poses[which[i]]`` ((K, 4, 4) T_world_cam) at scene time ``t_ns[which[i]]`` ((K,) int64):
        many poses and times in one batch of rays, each pixel as :meth:`render` gives it (up to
        float rounding).  The per-pixel sampler's renderer (``sim.sampling.simulate_pixels``):
        it has no plan to keep, every sample is evaluated at its ray's own time."""
        from ..geometry.poses import check_rigid

        poses = check_rigid(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4), "T_world_cam")
        which = np.asarray(which, dtype=np.int64)
        pixels = np.asarray(pixels, dtype=np.int64)
        n_pix = self.camera.width * self.camera.height
        if which.shape != pixels.shape or pixels.ndim != 1:
            raise InputError(f"{self.source}: pixels and pose indices must be two 1-D arrays of one length "
                             f"(got {pixels.shape} and {which.shape})")
        if pixels.size and (pixels.min() < 0 or pixels.max() >= n_pix or which.min() < 0
                            or which.max() >= poses.shape[0]):
            raise InputError(f"{self.source}: a pixel index is outside 0..{n_pix - 1} or a pose index outside "
                             f"0..{poses.shape[0] - 1}")
        tn = torch.from_numpy(self.normalized_times(t_ns)).to(self.device)
        if tn.numel() != poses.shape[0]:
            raise InputError(f"{self.source}: {tn.numel()} times for {poses.shape[0]} poses")
        s = self.pixel_samples
        if s > 1:                  # each pixel's sub-pixel rays (pixels of ray_camera), then their mean
            grey = self._render_rays(poses, tn, np.repeat(which, s * s), subpixels(self.camera.width, pixels, s).reshape(-1))
            return pixel_means(grey, s)
        return self._render_rays(poses, tn, which, pixels)

    def _render_rays(self, poses, tn, which, pixels) -> np.ndarray:
        """``render_pixels`` of pixels of ``ray_camera`` (checked, times normalised)."""
        if self.compiled_rays:
            return self._render_pixels_compiled(poses, tn, which, pixels)
        with torch.no_grad():
            o, d = pixel_rays(self.ray_camera, poses, which, pixels, device=self.device)
            ray_time = tn[torch.as_tensor(which, device=self.device)]
            out, rays = self._backdrop_and_rays(o, d)
            out = out.clone()

            def decode(p):       # each dynamic sample at its ray's time
                t = ray_time[p.dyn_rays][torch.div(p.dyn_idx, p.width, rounding_mode="floor")]
                return self.field.decode(p.feats, t[:, None])

            for j in torch.split(rays, self.chunk):
                self._play(self._plan_chunk(o[j], d[j], j, out[j], playback=False), out, decode)
        self.rays_total += int(pixels.size)
        return np.maximum(out.cpu().numpy().astype(np.float32), 0.0)

    def _backdrop_of(self, poses, which, pixels) -> np.ndarray:
        """(M,) what single-pixel rays see beyond the box: the flat grey, else the background."""
        m = int(pixels.size)
        if self.flat_grey is not None:
            return np.full(m, self.flat_grey)
        with torch.no_grad():
            _, d = pixel_rays(self.ray_camera, poses, which, pixels)
            return torch.as_tensor(background_grey(self.field, d, self.background)).expand(m).numpy()

    def _camera_dirs(self) -> np.ndarray:
        if self._cam_dirs is None:
            self._cam_dirs = self.ray_camera.ray_directions(1).reshape(-1, 3)
        return self._cam_dirs

    def _render_pixels_compiled(self, poses, tn, which, pixels) -> np.ndarray:
        """``render_pixels`` with the geometry compiled, chunk by chunk of rays: a baked field's
        marched whole (``field.baked_rays``), any other field's samples placed by ``field.ray_samples``
        and evaluated by the field in one batch (``_field_chunk``); the tensor path's values up to
        float rounding."""
        m = int(pixels.size)
        self.rays_total += m
        backdrop = self._backdrop_of(poses, which, pixels)
        compiled = self._compiled_pass()
        if compiled is None:                # no cell can show anything: every ray sees the backdrop
            return np.maximum(backdrop, 0.0).astype(np.float32)
        threads = torch.get_num_threads()
        dirs = self._camera_dirs()[pixels]
        out = np.empty(m, np.float32)
        for a in range(0, m, self.chunk):
            b = min(a + self.chunk, m)
            if self._baked:
                out[a:b], counts = compiled(poses, tn.numpy(), which[a:b], dirs[a:b], backdrop[a:b], threads=threads)
            else:
                out[a:b], counts = self._field_chunk(compiled, poses, tn, which[a:b], dirs[a:b], backdrop[a:b], threads)
            self._count_traced(counts, b - a)
        return np.maximum(out, 0.0)

    def _field_chunk(self, placer, poses, tn, which, dirs, backdrop, threads):
        """(grey (M,), samples per ray (M,)) of a chunk of single-pixel rays through the field: its
        samples placed (``ray_samples.SamplePlacer``), the dynamic ones decoded at their ray's time
        (faded at a flat world's region boundary), the static ones by the static field, composited."""
        from .ray_samples import composite

        rs = placer(poses, which, dirs, threads=threads)
        x = torch.from_numpy(rs.x)
        sigma, grey = torch.zeros(x.shape[0]), torch.zeros(x.shape[0])
        with torch.no_grad():
            dyn = torch.from_numpy(rs.is_dynamic)
            d_idx = torch.nonzero(dyn).squeeze(1)
            if d_idx.numel():
                xd = x[d_idx]
                t = tn[torch.from_numpy(which)[torch.from_numpy(rs.ray)[d_idx]]]
                dens, g = self.field.decode(self.field.space_features(xd), t[:, None])
                if self.flat_grey is not None:
                    dens = dens * self.dynamic.inner_weight(xd)
                sigma[d_idx], grey[d_idx] = dens.float(), g.float()
            s_idx = torch.nonzero(~dyn).squeeze(1)
            if s_idx.numel():
                dens, g = self.field.decode_static(self.field.space_features(x[s_idx]))
                sigma[s_idx], grey[s_idx] = dens.float(), g.float()
        return composite(rs, sigma.numpy(), grey.numpy(), backdrop, threads=threads), rs.counts

    @property
    def _baked(self) -> bool:
        from .baked import BakedField

        return isinstance(self.field, BakedField)

    def _compiled_pass(self):
        """The compiled single-pixel pass of this set-up (made once): a baked field's
        ``BakedMarcher``, else a ``SamplePlacer``; None when no cell can show anything."""
        if self._compiled is None:
            cells = self._cached_cells_box()
            if cells is None:
                return None
            from .baked_rays import BakedMarcher
            from .ray_samples import SamplePlacer

            setup = dict(box=self.box, near=self.near, far=self.far, n_samples=self.n_samples, cells_box=cells,
                         occupancy=self.occupancy.occupied.numpy() if self.occupancy is not None
                         and self.occupancy.enabled else None,
                         dynamic=None if self.dynamic is None else self.dynamic.mask.numpy(),
                         flat=self.flat_grey is not None)
            self._compiled = BakedMarcher(self.field, **setup) if self._baked else SamplePlacer(**setup)
        return self._compiled

    def warm_up(self) -> None:
        """Load the compiled single-pixel passes (``compiled_rays``, a baked field's marcher) now
        rather than in the first ``render_pixels`` (~0.4 s from numba's cache; compiled once per
        machine, ~10 s): the publisher calls it before a per-pixel run."""
        if self.compiled_rays:
            compiled = self._compiled_pass()
            if compiled is not None:
                compiled.warm_up()

    def _count_traced(self, counts, m: int) -> None:
        """Count ``m`` single-pixel rays' work (``counts``: samples evaluated per ray) as the tensor
        path: leave-out traces only rays with a sample that can show anything; without it, every ray."""
        traced = int(np.count_nonzero(counts)) if self._skips_rays else m
        self.rays_rendered += traced
        self.samples_total += traced * self.n_samples
        self.samples_evaluated += int(counts.sum())


def _composite(sigma, grey, delta, background: torch.Tensor):
    """Rendered grey of rays from per-sample density and grey (``render.render_rays``'s rule);
    ``background``: (rays,) what each ray sees beyond the box."""
    w = volume_weights(sigma * delta[:, None])
    acc = w.sum(dim=1)
    return (w * grey).sum(dim=1) + (1.0 - acc) * background


def _on_device(grid, attr: str, device):
    """A copy of an OccupancyGrid / DynamicRegion whose boolean grid lives on ``device``."""
    if grid is None:
        return None
    g = getattr(grid, attr)
    if g.device == device:
        return grid
    import copy

    out = copy.copy(grid)
    setattr(out, attr, g.to(device))
    return out


__all__ = ["FieldRenderer", "PLAN_CACHE_BYTES", "STATIC_WORLDS", "resolve_static_world"]
