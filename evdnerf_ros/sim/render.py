"""Deterministic, vectorised ray-casting renderer of linear grey intensity, depth and mask.

``render(scene, T_world_cam, t_ns, camera, supersample=2) -> RenderResult`` and
``SceneRenderer(scene, camera, supersample)``, a :class:`evdnerf_ros.renderer.Renderer`:
``.render(T_world_cam, t_ns)`` (or calling it) -> (H, W) float32 intensity, the interface
the event generator uses; ``.render_result(T_world_cam, t_ns)`` adds depth and mask.

Per frame:

1. Object poses at ``t_ns`` (int64 ns; floats only for in-segment fractions, see
   ``trajectory.py``).
2. Primary rays, s x s per pixel (``camera.ray_directions``).  For every primitive only the
   rays inside the screen rectangle of its projected local bounding box are tested
   (exact: the projection of a convex box whose corners are all in front of the camera is
   the convex hull of the projected corners; otherwise every ray is tested).  This is the
   "leave out what the scene does not need" step; ``prefilter=False`` turns it off.
3. Analytic intersections in object coordinates (slab, unit-sphere transform, cylinder with
   caps, Moller-Trumbore) and a nearest-hit z-buffer.
4. Shading of the winners only: ``I = albedo * texture(p_obj) * (ambient + sum_l E_l *
   max(0, n . -L_l) * visible_l)``, hard shadows by casting one ray per lit point and
   light (bounding-sphere prefilter, convex primitives skip themselves).  Textures are
   evaluated in object coordinates (a point pulled 1 um inside the surface, so box faces
   on a checker boundary do not speckle); noise is a seeded integer hash (no RNG); an image
   texture is sampled bilinearly on the object's local xy plane (``image_grey``).
5. Background ``intensity * (1 + contrast * pattern(ray direction / scale))``.
6. The s x s samples are averaged in linear intensity.

Depth (metres along the ray, ``inf`` for background) and mask come from the pixel-centre
ray: the middle sample for odd s, one extra geometry-only pass for even s.  Everything is
float64 inside; intensity is returned as float32 and is strictly positive and finite
(ambient > 0, albedo > 0, texture contrast < 1, background > 0 are enforced by the
scene loader).  Two calls with the same arguments give bit-identical images.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import InputError
from ..renderer import CameraRenderer
from ..geometry.camera import PinholeCamera
from ..geometry.poses import check_rigid
from .scene import Scene, Texture

SHADOW_OFFSET = 1e-5        # metres along the normal before casting a shadow ray
TEXTURE_INSET = 1e-6        # metres inside the surface where textures are evaluated


@dataclass
class RenderResult:
    intensity: np.ndarray       # (H, W) float32 linear
    depth: np.ndarray           # (H, W) float32 metres along the ray, inf = background
    mask: np.ndarray            # (H, W) bool


@dataclass
class RenderStats:
    rays: int = 0               # primary rays cast (sub-samples)
    tests: int = 0              # ray x primitive intersection tests performed
    shadow_tests: int = 0


# ----------------------------------------------------------------------------- textures

_H1 = np.uint64(0x9E3779B97F4A7C15)
_H2 = np.uint64(0xC2B2AE3D27D4EB4F)
_H3 = np.uint64(0x165667B19E3779F9)
_H4 = np.uint64(0x27D4EB2F165667C5)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def _hash01(ix, iy, iz, seed: int) -> np.ndarray:
    """Deterministic hash of integer lattice points to [0, 1) (splitmix64 finaliser)."""
    with np.errstate(over="ignore"):
        x = (ix.astype(np.uint64) * _H1) ^ (iy.astype(np.uint64) * _H2) \
            ^ (iz.astype(np.uint64) * _H3) ^ (np.uint64(seed) * _H4)
        x ^= x >> np.uint64(30)
        x *= _M1
        x ^= x >> np.uint64(27)
        x *= _M2
        x ^= x >> np.uint64(31)
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def value_noise(p: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth value noise in [0, 1] at points p (N, 3) (lattice spacing 1)."""
    fl = np.floor(p)
    i = fl.astype(np.int64)
    f = p - fl
    w = f * f * (3.0 - 2.0 * f)
    out = np.zeros(p.shape[0])
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wx * wy * wz * _hash01(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return out


def image_grey(tex: Texture, p: np.ndarray) -> np.ndarray:
    """Grey level in [0, 1] of an image texture at object points p (N, 3): the picture spans
    x in [-w/2, w/2] (columns) and y in [h/2, -h/2] (rows, top row at +y); bilinear between
    texel centres, edge texels held up to the picture's border, 0.5 outside it."""
    img = tex.image
    rows, cols = img.shape
    w, h = tex.size
    u = (p[:, 0] / w + 0.5) * cols - 0.5
    v = (0.5 - p[:, 1] / h) * rows - 0.5
    inside = (np.abs(p[:, 0]) <= 0.5 * w) & (np.abs(p[:, 1]) <= 0.5 * h)
    u = np.clip(u, 0.0, cols - 1.0)
    v = np.clip(v, 0.0, rows - 1.0)
    u0 = np.minimum(np.floor(u).astype(np.int64), cols - 2) if cols > 1 else np.zeros(u.shape, np.int64)
    v0 = np.minimum(np.floor(v).astype(np.int64), rows - 2) if rows > 1 else np.zeros(v.shape, np.int64)
    fu, fv = u - u0, v - v0
    u1 = np.minimum(u0 + 1, cols - 1)
    v1 = np.minimum(v0 + 1, rows - 1)
    g = ((1 - fv) * ((1 - fu) * img[v0, u0] + fu * img[v0, u1])
         + fv * ((1 - fu) * img[v1, u0] + fu * img[v1, u1]))
    return np.where(inside, g, 0.5)


def texture_pattern(tex: Texture, p: np.ndarray) -> np.ndarray:
    """Pattern in [-1, 1] of a texture at points p (N, 3) (object coordinates / scale)."""
    if tex.kind == "image":
        return 2.0 * image_grey(tex, p) - 1.0
    q = p / tex.scale
    if tex.kind == "checker":
        par = np.floor(q).astype(np.int64).sum(axis=1) & 1
        return 1.0 - 2.0 * par
    if tex.kind == "stripes":
        par = np.floor(q[:, tex.axis]).astype(np.int64) & 1
        return 1.0 - 2.0 * par
    n = 0.65 * value_noise(q, tex.seed) + 0.35 * value_noise(2.03 * q + 17.17, tex.seed + 1)
    return 2.0 * n - 1.0


def texture_factor(tex: Texture | None, p: np.ndarray) -> np.ndarray | float:
    if tex is None:
        return 1.0
    return 1.0 + tex.contrast * texture_pattern(tex, p)


# ----------------------------------------------------------------------------- renderer

def _rows_mul(v: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``v @ M.T`` for (N, 3) rows and a 3x3 M, by columns.

    A BLAS matmul with an inner dimension of 3 gains nothing and starts OpenBLAS threads,
    which spin and collapse under CPU contention (measured: 2-10x slower frames on a
    shared 2-core machine).  Everything here stays single-threaded numpy."""
    return v[:, 0:1] * M[:, 0] + v[:, 1:2] * M[:, 1] + v[:, 2:3] * M[:, 2]


def _rows_dot(v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``v @ u`` for (N, 3) rows and a 3-vector, by columns."""
    return v[:, 0] * u[0] + v[:, 1] * u[1] + v[:, 2] * u[2]


@lru_cache(maxsize=16)
def _ray_dirs(camera: PinholeCamera, s: int) -> np.ndarray:
    d = camera.ray_directions(s)
    d.setflags(write=False)
    return d


class SceneRenderer(CameraRenderer):
    """Renders one scene through one camera (a :class:`evdnerf_ros.renderer.Renderer`):
    ``render(T_world_cam, t_ns)`` / ``__call__`` -> intensity; ``render_result`` -> intensity,
    depth and mask."""

    def __init__(self, scene: Scene, camera: PinholeCamera | None = None, supersample: int = 2,
                 *, prefilter: bool = True, shadows: bool | None = None):
        if int(supersample) < 1:
            raise InputError(f"supersample must be >= 1, got {supersample}")
        self.scene = scene
        self.camera = camera if camera is not None else scene.camera
        self.supersample = int(supersample)
        self.prefilter = bool(prefilter)
        self.shadows = scene.lights.shadows if shadows is None else bool(shadows)
        self.stats = RenderStats()
        self._bg_cache: tuple[bytes, int, np.ndarray] | None = None

    # public -----------------------------------------------------------------------
    def render(self, T_world_cam, t_ns) -> np.ndarray:
        """(H, W) float32 linear intensity at int64-ns time ``t_ns`` (the Renderer interface)."""
        return self.render_result(T_world_cam, t_ns, geometry=False).intensity


    def render_result(self, T_world_cam, t_ns, *, geometry: bool = True) -> RenderResult:
        """Intensity and, with ``geometry``, depth and mask (else both None)."""
        if isinstance(t_ns, (bool, float, np.floating)) or not isinstance(t_ns, (int, np.integer)):
            raise InputError(f"render time must be int64 nanoseconds; got {t_ns!r}")
        T = check_rigid(T_world_cam, "T_world_cam")
        t = int(t_ns)
        s = self.supersample
        leaves = self.scene.leaves
        tfs = self.scene.leaf_transforms(t)
        self._check_camera_outside(T, tfs, t)
        cam = self.camera
        dirs = _ray_dirs(cam, s)
        tbest, ibest, aux, rects = self._cast(dirs, T, leaves, tfs, s)
        img = self._shade(dirs, T, leaves, tfs, tbest, ibest, aux, rects)
        H, W = cam.height, cam.width
        intensity = img.reshape(H, s, W, s).mean(axis=(1, 3)).astype(np.float32)
        if not geometry:
            return RenderResult(intensity, None, None)
        if s % 2 == 1:
            c = s // 2
            depth, ids = tbest[c::s, c::s], ibest[c::s, c::s]
        else:
            depth, ids, _, _ = self._cast(_ray_dirs(cam, 1), T, leaves, tfs, 1)
        return RenderResult(intensity, depth.astype(np.float32), ids >= 0)

    # internals ----------------------------------------------------------------------
    def _check_camera_outside(self, T, tfs, t):
        c = T[:3, 3]
        for o, Tw in zip(self.scene.leaves, tfs):
            local = (c - Tw[:3, 3]) @ Tw[:3, :3]
            if o.shape.contains(local[None])[0]:
                raise InputError(f"{self.scene.source}: camera at ({c[0]:.3f}, {c[1]:.3f}, "
                                 f"{c[2]:.3f}) m is inside object {o.name!r} at t = "
                                 f"{t / 1e9:.9f} s; choose a pose outside the objects")

    def _rect(self, shape, Tw, T, H, W, s):
        """Sub-sample rows/cols [r0, r1) x [c0, c1) that can see the primitive, or None."""
        if not self.prefilter:
            return 0, H, 0, W
        corners = shape.corners() @ Tw[:3, :3].T + Tw[:3, 3]
        pc = (corners - T[:3, 3]) @ T[:3, :3]
        z = pc[:, 2]
        if np.all(z <= 1e-9):
            return None
        if np.any(z <= 1e-9):
            return 0, H, 0, W
        cam = self.camera
        u = cam.fx * pc[:, 0] / z + cam.cx
        v = cam.fy * pc[:, 1] / z + cam.cy
        c0 = max(0, int(np.floor((u.min() + 0.5) * s - 0.5)) - 1)
        c1 = min(W, int(np.ceil((u.max() + 0.5) * s - 0.5)) + 2)
        r0 = max(0, int(np.floor((v.min() + 0.5) * s - 0.5)) - 1)
        r1 = min(H, int(np.ceil((v.max() + 0.5) * s - 0.5)) + 2)
        if c0 >= c1 or r0 >= r1:
            return None
        return r0, r1, c0, c1

    def _cast(self, dirs, T, leaves, tfs, s):
        H, W = dirs.shape[:2]
        tbest = np.full((H, W), np.inf)
        ibest = np.full((H, W), -1, dtype=np.int32)
        aux = None
        rects = []
        Rwc, o_w = T[:3, :3], T[:3, 3]
        self.stats.rays += H * W
        for i, (obj, Tw) in enumerate(zip(leaves, tfs)):
            rect = self._rect(obj.shape, Tw, T, H, W, s)
            rects.append(rect)
            if rect is None:
                continue
            r0, r1, c0, c1 = rect
            Rwo = Tw[:3, :3]
            M = Rwo.T @ Rwc                         # camera -> object directions
            d_l = _rows_mul(dirs[r0:r1, c0:c1].reshape(-1, 3), M)
            o_l = Rwo.T @ (o_w - Tw[:3, 3])
            self.stats.tests += d_l.shape[0]
            t, a = obj.shape.intersect(o_l, d_l)
            t = t.reshape(r1 - r0, c1 - c0)
            tb = tbest[r0:r1, c0:c1]
            closer = t < tb
            if not np.any(closer):
                continue
            tb[closer] = t[closer]
            ibest[r0:r1, c0:c1][closer] = i
            if a is not None:
                if aux is None:
                    aux = np.full((H, W), -1, dtype=np.int64)
                aux[r0:r1, c0:c1][closer] = a.reshape(r1 - r0, c1 - c0)[closer]
        return tbest, ibest, aux, rects

    def _background(self, dirs, T) -> np.ndarray | float:
        bg = self.scene.background
        if bg.texture is None:
            return bg.intensity
        key = T.tobytes()
        if self._bg_cache is not None and self._bg_cache[0] == key \
                and self._bg_cache[1] == dirs.shape[0]:
            return self._bg_cache[2]
        d_w = _rows_mul(dirs.reshape(-1, 3), T[:3, :3])
        img = (bg.intensity * texture_factor(bg.texture, d_w)).reshape(dirs.shape[:2])
        self._bg_cache = (key, dirs.shape[0], img)
        return img

    def _shade(self, dirs, T, leaves, tfs, tbest, ibest, aux, rects):
        H, W = dirs.shape[:2]
        img = np.empty((H, W))
        img[...] = self._background(dirs, T)
        lights = self.scene.lights
        Rwc, o_w = T[:3, :3], T[:3, 3]
        for i, (obj, Tw, rect) in enumerate(zip(leaves, tfs, rects)):
            if rect is None:
                continue
            r0, r1, c0, c1 = rect
            m = ibest[r0:r1, c0:c1] == i
            if not np.any(m):
                continue
            Rwo, p_wo = Tw[:3, :3], Tw[:3, 3]
            d_c = dirs[r0:r1, c0:c1][m]
            t = tbest[r0:r1, c0:c1][m]
            d_w = _rows_mul(d_c, Rwc)
            d_l = _rows_mul(d_w, Rwo.T)
            o_l = Rwo.T @ (o_w - p_wo)
            p_l = o_l + t[:, None] * d_l
            a = aux[r0:r1, c0:c1][m] if aux is not None else None
            n_l = obj.shape.normal(p_l, d_l, a)
            n_w = _rows_mul(n_l, Rwo)
            albedo = obj.albedo * texture_factor(obj.texture, p_l - TEXTURE_INSET * n_l)
            shade = np.full(t.shape[0], lights.ambient)
            p_w = None
            for light in lights.directional:
                if light.intensity == 0:
                    continue
                ndl = np.maximum(0.0, -_rows_dot(n_w, light.direction))
                if self.shadows:
                    lit = np.nonzero(ndl > 0)[0]
                    if lit.size:
                        if p_w is None:
                            p_w = o_w + t[:, None] * d_w + SHADOW_OFFSET * n_w
                        occ = self._occluded(p_w[lit], -light.direction, leaves, tfs,
                                             skip=i if obj.shape.convex else -1)
                        ndl[lit[occ]] = 0.0
                shade += light.intensity * ndl
            img[r0:r1, c0:c1][m] = albedo * shade
        return img

    def _occluded(self, origins, direction, leaves, tfs, skip) -> np.ndarray:
        occ = np.zeros(origins.shape[0], dtype=bool)
        for j, (obj, Tw) in enumerate(zip(leaves, tfs)):
            if j == skip:
                continue
            Rwo, p_wo = Tw[:3, :3], Tw[:3, 3]
            c_l, rad = obj.shape.bounding_sphere()
            oc = (Rwo @ c_l + p_wo) - origins
            tca = _rows_dot(oc, direction)
            d2 = np.einsum("ij,ij->i", oc, oc) - tca * tca
            cand = ~occ & (d2 <= rad * rad) & (tca >= -rad)
            idx = np.nonzero(cand)[0]
            if idx.size == 0:
                continue
            self.stats.shadow_tests += idx.size
            o_l = _rows_mul(origins[idx] - p_wo, Rwo.T)
            d_l = np.broadcast_to(Rwo.T @ direction, o_l.shape)
            t, _ = obj.shape.intersect(o_l, d_l)
            occ[idx] |= np.isfinite(t)
        return occ


def render(scene: Scene, T_world_cam, t_ns, camera: PinholeCamera | None = None, *,
           supersample: int = 2, prefilter: bool = True) -> RenderResult:
    """Render intensity, depth and mask of ``scene`` at int64-ns time ``t_ns``."""
    return SceneRenderer(scene, camera, supersample, prefilter=prefilter).render_result(
        T_world_cam, t_ns)
