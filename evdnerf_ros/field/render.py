"""Rays, ray-box intersection, sampling and volume rendering inside the scene box.

Conventions: ``T_world_cam`` is 4x4 (camera -> world, OpenCV camera axes), pixel centres
at integer coordinates (``sim.camera.PinholeCamera``).  The scene box is axis-aligned,
``box = (min_xyz, max_xyz)`` in metres.  Fields see box-normalised coordinates in
[-1, 1]; densities are per metre of world distance.

Sampling: the part of each ray inside the box, clipped to [near, far], is split into
``n_samples`` equal bins; one sample per bin, at the bin centre (``perturb=False``) or at
a uniform random position in the bin (stratified, ``perturb=True``).  Each sample stands
for its whole bin (delta = bin length), so a constant density sigma gives opacity exactly
``1 - exp(-sigma * length)``.  Rays that miss the box (or whose clipped interval is empty)
render the background.

Rendered grey = sum_i w_i c_i + (1 - sum_i w_i) * background, linear intensity, where
background is the field's learned ``BackgroundMap`` of the ray direction when it has one
(``field.background_map``), else the constant ``background``.

Static-view reuse: ``render_rays`` accepts a list of times; all of them share the same
samples and the field's space features (``DynamicField.evaluate_times``).

Static regions: with a ``DynamicRegion``, samples outside it take the static field,
evaluated once for all times.  With ``changes_only`` (the caller uses only differences
between the times), rays with no dynamic sample are not evaluated at all: they render the
background at every time, so their change is exactly zero, as the full render's would be.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .base import DynamicField, as_time_column


def box_tensors(box, device=None):
    lo = torch.as_tensor(np.asarray(box[0], dtype=np.float64), dtype=torch.float32,
                         device=device)
    hi = torch.as_tensor(np.asarray(box[1], dtype=np.float64), dtype=torch.float32,
                         device=device)
    if lo.shape != (3,) or hi.shape != (3,) or not bool(torch.all(hi > lo)):
        raise ValueError(f"scene box must be (min xyz, max xyz) with max > min, got {box}")
    return lo, hi


def camera_rays(camera, T_world_cam, supersample: int = 1, device=None):
    """World-frame rays of every pixel: origins, unit dirs, each (H*W, 3) float32 (row-major)."""
    d_cam = camera.ray_directions(supersample).reshape(-1, 3)        # float64
    T = np.asarray(T_world_cam, dtype=np.float64)
    d = d_cam @ T[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(T[:3, 3], d.shape)
    return (torch.as_tensor(np.ascontiguousarray(o), dtype=torch.float32, device=device),
            torch.as_tensor(d, dtype=torch.float32, device=device))


def subpixels(width: int, pixels, s: int) -> np.ndarray:
    """(M, s*s) row-major indices, in the image ``s`` times finer (``camera.resized``), of the
    sub-pixels covering row-major ``pixels`` of an image ``width`` wide (their centres are
    ``PinholeCamera.ray_directions(s)``'s)."""
    pixels = np.asarray(pixels, np.int64).reshape(-1)
    i = np.arange(int(s))
    rows = (pixels // width)[:, None, None] * s + i[None, :, None]
    cols = (pixels % width)[:, None, None] * s + i[None, None, :]
    return (rows * (width * s) + cols).reshape(-1, s * s)


def pixel_means(values, s: int):
    """(M * s*s, ...) values of sub-pixel rays grouped pixel by pixel -> (M, ...) their means:
    the brightness a pixel gathers over its area (``TrainConfig.pixel_samples``)."""
    if s == 1:
        return values
    return values.reshape(-1, s * s, *values.shape[1:]).mean(1)


def finer(camera, s: int):
    """The camera whose pixels are ``camera``'s sub-pixels (the same field of view, s x s finer)."""
    return camera if s == 1 else camera.resized(camera.width * s, camera.height * s)


def area_rays(camera, T_world_cam, s: int = 1, device=None):
    """:func:`camera_rays` of every pixel's s x s sub-pixels, grouped pixel by pixel: origins and
    unit dirs, each (H*W*s*s, 3) float32 (s = 1: the pixel centres' rays)."""
    o, d = camera_rays(finer(camera, s), T_world_cam, device=device)
    if s > 1:
        order = torch.as_tensor(subpixels(camera.width, np.arange(camera.width * camera.height), s).reshape(-1),
                                device=o.device)
        o, d = o[order], d[order]
    return o, d


def pixel_rays(camera, poses, which, pixels, device=None):
    """World-frame rays of single pixels seen from several poses: pixel ``pixels[i]`` (row-major
    index) from pose ``poses[which[i]]`` ((K, 4, 4) T_world_cam); origins and unit dirs, each
    (M, 3) float32, each ray as :func:`camera_rays` gives it."""
    d_cam = camera.ray_directions(1).reshape(-1, 3)[np.asarray(pixels)]      # float64
    T = np.asarray(poses, dtype=np.float64)[np.asarray(which)]
    d = np.einsum("mj,mij->mi", d_cam, T[:, :3, :3])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return (torch.as_tensor(np.ascontiguousarray(T[:, :3, 3]), dtype=torch.float32, device=device),
            torch.as_tensor(d, dtype=torch.float32, device=device))


def ray_box_intersect(origins: torch.Tensor, dirs: torch.Tensor, box, near: float = 0.0,
                      far: float = float("inf")):
    """Slab intersection of rays with the box, clipped to [near, far].

    Returns (t_near (N,), t_far (N,), hit (N,) bool); for misses both distances are 0 and
    ``hit`` is False.  Distances are in units of |dir|; a ray starting inside the box
    enters at max(0, near).
    """
    lo, hi = box_tensors(box, origins.device)
    d = dirs.to(torch.float32)
    tiny = 1e-12
    d_safe = torch.where(d.abs() < tiny, torch.where(d < 0, -tiny, tiny), d)
    inv = 1.0 / d_safe
    t0 = (lo - origins) * inv
    t1 = (hi - origins) * inv
    t_enter = torch.minimum(t0, t1).amax(dim=1).clamp(min=float(near))
    t_exit = torch.maximum(t0, t1).amin(dim=1).clamp(max=float(far))
    hit = t_exit > t_enter
    t_enter = torch.where(hit, t_enter, torch.zeros_like(t_enter))
    t_exit = torch.where(hit, t_exit, torch.zeros_like(t_exit))
    return t_enter, t_exit, hit


def normalize_points(points: torch.Tensor, box) -> torch.Tensor:
    """World points -> box-normalised [-1, 1] (clamped)."""
    lo, hi = box_tensors(box, points.device)
    return ((points - lo) / (hi - lo) * 2.0 - 1.0).clamp(-1.0, 1.0)


def background_grey(field: DynamicField, dirs: torch.Tensor, background: float):
    """What rays leaving the box unoccluded see: the field's learned background map of the
    ray direction ((N,) tensor) when it has one, else the constant ``background``."""
    bg_map = getattr(field, "background_map", None)
    return background if bg_map is None else bg_map(dirs)


def flat_background(field, background: float) -> float:
    """The one grey of a flat static world: the field's learned background map averaged over
    the sphere (directions on a Fibonacci lattice, equal area each), else ``background``."""
    bg_map = getattr(field, "background_map", None)
    if bg_map is None:
        return float(background)
    n = 4096
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / n
    r = torch.sqrt(1.0 - z * z)
    phi = k * (math.pi * (3.0 - math.sqrt(5.0)))
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=1).to(torch.float32)
    with torch.no_grad():
        return float(bg_map(dirs.to(next(bg_map.parameters()).device)).mean())


def sample_along_rays(t_near, t_far, n_samples: int, perturb: bool = False,
                      generator: torch.Generator | None = None):
    """(N, S) sample distances and (N,) bin length."""
    n = t_near.shape[0]
    u = (torch.rand(n, n_samples, generator=generator, device=t_near.device) if perturb
         else torch.full((n, n_samples), 0.5, device=t_near.device))
    bins = torch.arange(n_samples, dtype=torch.float32, device=t_near.device)
    delta = (t_far - t_near) / n_samples
    z = t_near[:, None] + (bins[None, :] + u) * delta[:, None]
    return z, delta


def volume_weights(sigma_delta: torch.Tensor) -> torch.Tensor:
    """(N, S) optical depths sigma_i * delta_i -> weights T_i * alpha_i."""
    alpha = -torch.expm1(-sigma_delta)
    cum = torch.cumsum(sigma_delta, dim=1)
    excl = torch.cat([torch.zeros_like(cum[:, :1]), cum[:, :-1]], dim=1)
    return alpha * torch.exp(-excl)


def render_rays(field: DynamicField, origins: torch.Tensor, dirs: torch.Tensor, t_norm,
                box, n_samples: int = 64, *, near: float = 0.0, far: float = float("inf"),
                background: float = 0.0, perturb: bool = False,
                generator: torch.Generator | None = None, occupancy=None, dynamic=None,
                changes_only: bool = False, flat_background: float | None = None):
    """Render rays at one time or at several times sharing their samples.

    ``t_norm``: a float, an (N,) / (N, 1) tensor, or a list/tuple of those (static-view
    reuse: one result per time, samples and space features shared).
    ``occupancy``: an ``OccupancyGrid`` (or None); samples in empty cells are not
    evaluated (density 0).  ``dynamic``: a ``DynamicRegion`` (or None); ``changes_only``:
    see the module docstring (needs ``dynamic``).  ``flat_background`` (needs ``dynamic``): a
    flat static world, every sample outside the region empty, the density inside it fading to 0
    at its boundary (``DynamicRegion.inner_weight``), and every ray ending on this grey
    (``FieldRenderer``'s ``static_world="flat"``).

    Returns a dict (or a list of dicts for a list of times) with ``grey`` (N,),
    ``opacity`` (N,), ``depth`` (N,, expected distance; background rays -> 0),
    ``weights`` (N, S), ``z`` (N, S).
    """
    multi = isinstance(t_norm, (list, tuple))
    times = list(t_norm) if multi else [t_norm]
    n = origins.shape[0]
    t_near, t_far, hit = ray_box_intersect(origins, dirs, box, near, far)
    z, delta = sample_along_rays(t_near, t_far, n_samples, perturb, generator)
    pts = origins[:, None, :] + dirs[:, None, :] * z[..., None]          # (N, S, 3)
    x = normalize_points(pts.reshape(-1, 3), box)
    valid = hit[:, None].expand(n, n_samples).reshape(-1)
    if occupancy is not None:
        valid = valid & occupancy.query(x)
    is_dynamic = None
    if dynamic is not None:
        is_dynamic = dynamic.query(x) & valid
        if changes_only:
            ray_dynamic = is_dynamic.reshape(n, n_samples).any(dim=1)
            valid = valid & ray_dynamic[:, None].expand(n, n_samples).reshape(-1)
        if flat_background is not None:
            valid = valid & is_dynamic
    elif changes_only or flat_background is not None:
        raise ValueError("changes_only and flat_background need a dynamic region")
    idx = torch.nonzero(valid, as_tuple=False).squeeze(1)
    ray_of_sample = torch.div(idx, n_samples, rounding_mode="floor")
    t_cols = [as_time_column(t, n, origins.device)[ray_of_sample] for t in times]
    if idx.numel():
        evals = field.evaluate_times(x[idx], t_cols,
                                     None if is_dynamic is None else is_dynamic[idx])
    else:
        evals = [(None, None)] * len(times)
    bg = background_grey(field, dirs, background) if flat_background is None else float(flat_background)
    # a flat world's region fades out at its boundary (``DynamicRegion.inner_weight``)
    fade = dynamic.inner_weight(x[idx]) if flat_background is not None and idx.numel() else None
    out = []
    for dens_v, grey_v in evals:
        sigma = torch.zeros(n * n_samples, dtype=torch.float32, device=origins.device)
        grey = torch.zeros_like(sigma)
        if dens_v is not None:
            if fade is not None:
                dens_v = dens_v * fade
            sigma = sigma.index_put((idx,), dens_v)
            grey = grey.index_put((idx,), grey_v)
        sigma = sigma.reshape(n, n_samples)
        grey = grey.reshape(n, n_samples)
        w = volume_weights(sigma * delta[:, None])
        acc = w.sum(dim=1)
        out.append({"grey": (w * grey).sum(dim=1) + (1.0 - acc) * bg,
                    "opacity": acc, "depth": (w * z).sum(dim=1), "weights": w, "z": z})
    return out if multi else out[0]


def render_image(field: DynamicField, camera, T_world_cam, t_norm, box,
                 n_samples: int = 64, *, chunk: int = 8192, near: float = 0.0,
                 far: float = float("inf"), background: float = 0.0, occupancy=None,
                 dynamic=None, changes_only: bool = False, flat_background: float | None = None,
                 with_grad: bool = False, key: str = "grey", pixel_samples: int = 1):
    """Render a full image (H, W) float32 of ``key`` ("grey", "opacity" or "depth").

    ``t_norm`` as in ``render_rays`` (a list gives a list of images from shared samples).
    Deterministic (bin-centre samples); chunked over rays; no autograd unless
    ``with_grad``.  ``pixel_samples``: each pixel the mean of that many sub-pixel rays per side.
    """
    multi = isinstance(t_norm, (list, tuple))
    times = list(t_norm) if multi else [t_norm]
    from ..device import module_device

    sub = int(pixel_samples)
    o, d = area_rays(camera, T_world_cam, sub, device=module_device(field))     # the field's device
    parts: list[list[torch.Tensor]] = [[] for _ in times]
    with torch.set_grad_enabled(with_grad):
        for s in range(0, o.shape[0], chunk):
            res = render_rays(field, o[s:s + chunk], d[s:s + chunk], times, box, n_samples,
                              near=near, far=far, background=background,
                              occupancy=occupancy, dynamic=dynamic, changes_only=changes_only,
                              flat_background=flat_background)
            for k, r in enumerate(res):
                parts[k].append(r[key])
    imgs = [pixel_means(torch.cat(p), sub).reshape(camera.height, camera.width) for p in parts]
    return imgs if multi else imgs[0]
