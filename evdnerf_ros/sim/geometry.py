"""Primitives in their own (local) coordinates and vectorised ray intersection.

Every primitive is centred on its local origin:

* ``Box(size)``            axis-aligned box, full edge lengths ``size = (sx, sy, sz)``;
* ``Ellipsoid(radii)``     ``(x/a)^2 + (y/b)^2 + (z/c)^2 <= 1`` (a sphere when a = b = c);
* ``Cylinder(radius, height)`` around the local z axis, ``|z| <= height / 2``, with caps;
* ``Mesh(vertices, faces)`` a triangle mesh (Moller-Trumbore, vectorised rays x triangles).

``intersect(o, d)`` takes ray origins ``o`` (3,) or (N, 3) and unit directions ``d``
(N, 3) in local coordinates and returns the nearest hit distance ``t`` (N,) with
``t > tmin`` (``inf`` for a miss) and an auxiliary int array (the triangle index for
meshes, else ``None``).  Rigid transforms keep distances, so ``t`` is also the distance
along the world ray.  ``normal(p, d, aux)`` gives outward unit normals at local hit points
(mesh normals are turned towards the incoming ray: meshes need not be closed or
consistently oriented).  ``contains(p)`` tests points (meshes: ray parity, which assumes a
closed mesh).
"""

from __future__ import annotations

import abc

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

TMIN = 1e-9
_MT_CHUNK = 1 << 21        # rays x triangles per Moller-Trumbore block (memory bound)


def _as_rays(o, d):
    d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(o, dtype=np.float64)
    o = np.broadcast_to(o.reshape(-1, 3), d.shape) if o.size == 3 else o.reshape(-1, 3)
    return o, d


class Primitive(abc.ABC):
    convex = True
    kind = "primitive"

    @abc.abstractmethod
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        ...

    def corners(self) -> np.ndarray:
        lo, hi = self.bounds()
        idx = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        return np.where(idx == 0, lo, hi)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        lo, hi = self.bounds()
        return 0.5 * (lo + hi), float(0.5 * np.linalg.norm(hi - lo))

    @abc.abstractmethod
    def intersect(self, o, d, tmin: float = TMIN):
        ...

    @abc.abstractmethod
    def normal(self, p, d=None, aux=None) -> np.ndarray:
        ...

    def contains(self, p) -> np.ndarray:
        ...


@dataclass
class Box(Primitive):
    size: np.ndarray
    kind = "box"

    def __post_init__(self):
        self.size = np.asarray(self.size, dtype=np.float64).reshape(3)
        self.half = 0.5 * self.size

    def bounds(self):
        return -self.half, self.half.copy()

    def intersect(self, o, d, tmin: float = TMIN):
        d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
        o = np.asarray(o, dtype=np.float64)
        o = o.reshape(3) if o.size == 3 else o.reshape(-1, 3)
        return slab(o, d, -self.half, self.half, tmin), None

    def normal(self, p, d=None, aux=None):
        p = np.asarray(p, dtype=np.float64)
        r = np.abs(p) / self.half
        axis = np.argmax(r, axis=1)
        n = np.zeros_like(p)
        rows = np.arange(p.shape[0])
        n[rows, axis] = np.sign(p[rows, axis])
        n[rows, axis] = np.where(n[rows, axis] == 0, 1.0, n[rows, axis])
        return n

    def contains(self, p):
        return np.all(np.abs(np.asarray(p, dtype=np.float64)) <= self.half, axis=-1)


def _slab_range(o, d, lo, hi):
    """Entry and exit distances of rays through an axis-aligned box (per-axis columns)."""
    tn = tf = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            dk = d[:, k]
            inv = 1.0 / dk
            ok = o[:, k] if o.ndim == 2 else o[k]
            a = (lo[k] - ok) * inv
            b = (hi[k] - ok) * inv
            near, far = np.fmin(a, b), np.fmax(a, b)
            tn = near if tn is None else np.fmax(tn, near)
            tf = far if tf is None else np.fmin(tf, far)
    return tn, tf


def slab(o, d, lo, hi, tmin: float = TMIN) -> np.ndarray:
    """Ray / axis-aligned box: the first crossing distance > tmin, else inf."""
    tn, tf = _slab_range(o, d, lo, hi)
    hit = (tf >= tn) & (tf > tmin)
    t = np.where(tn > tmin, tn, tf)
    return np.where(hit, t, np.inf)


def slab_any(o, d, lo, hi) -> np.ndarray:
    """Boolean: does the ray (t >= 0) touch the box at all (prefilter)."""
    tn, tf = _slab_range(o, d, lo, hi)
    return (tf >= tn) & (tf >= 0)


@dataclass
class Ellipsoid(Primitive):
    radii: np.ndarray
    kind = "ellipsoid"

    def __post_init__(self):
        self.radii = np.asarray(self.radii, dtype=np.float64).reshape(3)
        self.inv_r = 1.0 / self.radii

    def bounds(self):
        return -self.radii, self.radii.copy()

    def bounding_sphere(self):
        return np.zeros(3), float(self.radii.max())

    def intersect(self, o, d, tmin: float = TMIN):
        d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
        o = np.asarray(o, dtype=np.float64)
        ir = self.inv_r
        dx, dy, dz = d[:, 0] * ir[0], d[:, 1] * ir[1], d[:, 2] * ir[2]
        a = dx * dx + dy * dy + dz * dz
        if o.size == 3:
            ox, oy, oz = o.reshape(3) * ir
        else:
            o = o.reshape(-1, 3)
            ox, oy, oz = o[:, 0] * ir[0], o[:, 1] * ir[1], o[:, 2] * ir[2]
        b = ox * dx + oy * dy + oz * dz               # half of the usual b
        c = ox * ox + oy * oy + oz * oz - 1.0
        disc = b * b - a * c
        hit = disc >= 0
        sq = np.sqrt(np.where(hit, disc, 0.0))
        # numerically stable roots: q = -(b + sign(b) sq); t = q / a and c / q
        q = -(b + np.copysign(sq, b))
        with np.errstate(divide="ignore", invalid="ignore"):
            r1 = q / a
            r2 = np.where(q != 0, c / q, -np.inf)
        t0 = np.minimum(r1, r2)
        t1 = np.maximum(r1, r2)
        t = np.where(t0 > tmin, t0, np.where(t1 > tmin, t1, np.inf))
        return np.where(hit, t, np.inf), None

    def normal(self, p, d=None, aux=None):
        n = np.asarray(p, dtype=np.float64) * (self.inv_r * self.inv_r)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def contains(self, p):
        p = np.asarray(p, dtype=np.float64) * self.inv_r
        return np.sum(p * p, axis=-1) <= 1.0


class Sphere(Ellipsoid):
    kind = "sphere"

    def __init__(self, radius: float):
        super().__init__(np.full(3, float(radius)))
        self.radius = float(radius)


@dataclass
class Cylinder(Primitive):
    radius: float
    height: float
    kind = "cylinder"

    def __post_init__(self):
        self.radius = float(self.radius)
        self.height = float(self.height)
        self.hz = 0.5 * self.height

    def bounds(self):
        e = np.array([self.radius, self.radius, self.hz])
        return -e, e.copy()

    def intersect(self, o, d, tmin: float = TMIN):
        o, d = _as_rays(o, d)
        ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - self.radius * self.radius
        disc = b * b - a * c
        ok = (disc >= 0) & (a > 0)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        best = np.full(o.shape[0], np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for sgn in (-1.0, 1.0):
                ts = (-b + sgn * sq) / a
                z = oz + ts * dz
                good = ok & (ts > tmin) & (np.abs(z) <= self.hz)
                best = np.where(good & (ts < best), ts, best)
            for zc in (-self.hz, self.hz):
                tc = (zc - oz) / dz
                x = ox + tc * dx
                y = oy + tc * dy
                good = (dz != 0) & (tc > tmin) & (x * x + y * y <= self.radius * self.radius)
                best = np.where(good & (tc < best), tc, best)
        return best, None

    def normal(self, p, d=None, aux=None):
        p = np.asarray(p, dtype=np.float64)
        rho = np.hypot(p[:, 0], p[:, 1])
        cap = (self.hz - np.abs(p[:, 2])) < (self.radius - rho)
        n = np.zeros_like(p)
        safe = np.where(rho > 0, rho, 1.0)
        n[:, 0] = np.where(cap, 0.0, p[:, 0] / safe)
        n[:, 1] = np.where(cap, 0.0, p[:, 1] / safe)
        n[:, 2] = np.where(cap, np.sign(p[:, 2]) + (p[:, 2] == 0), 0.0)
        return n

    def contains(self, p):
        p = np.asarray(p, dtype=np.float64)
        return ((p[..., 0] ** 2 + p[..., 1] ** 2 <= self.radius ** 2)
                & (np.abs(p[..., 2]) <= self.hz))


@dataclass
class Mesh(Primitive):
    vertices: np.ndarray          # (V, 3) float64
    faces: np.ndarray             # (F, 3) int
    source: str = ""
    kind = "mesh"
    convex = False
    _tri: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        v = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        where = f"{self.source}: " if self.source else ""
        if v.shape[0] == 0 or f.shape[0] == 0:
            raise InputError(f"{where}mesh has no triangles; give a mesh with faces")
        if not np.all(np.isfinite(v)):
            raise InputError(f"{where}mesh has non-finite vertex coordinates")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise InputError(f"{where}mesh faces index vertices that do not exist")
        tri = v[f]
        e1 = tri[:, 1] - tri[:, 0]
        e2 = tri[:, 2] - tri[:, 0]
        fn = np.cross(e1, e2)
        area = np.linalg.norm(fn, axis=1)
        keep = area > 1e-18
        if not np.any(keep):
            raise InputError(f"{where}mesh has only degenerate (zero-area) triangles")
        self.vertices, self.faces = v, f[keep]
        self._v0 = tri[keep, 0]
        self._e1 = e1[keep]
        self._e2 = e2[keep]
        self._fn = fn[keep] / area[keep, None]
        self._lo = v[np.unique(self.faces)].min(axis=0)
        self._hi = v[np.unique(self.faces)].max(axis=0)

    @property
    def n_triangles(self) -> int:
        return int(self.faces.shape[0])

    def bounds(self):
        return self._lo.copy(), self._hi.copy()

    def _mt(self, o, d, tmin, first=True):
        """Moller-Trumbore over all rays x triangles in blocks; nearest t and face id."""
        n = o.shape[0]
        best = np.full(n, np.inf)
        face = np.full(n, -1, dtype=np.int64)
        count = np.zeros(n, dtype=np.int64)
        nf = self._v0.shape[0]
        rays_per_block = max(1, _MT_CHUNK // max(nf, 1))
        tris_per_block = max(1, min(nf, _MT_CHUNK))
        for r0 in range(0, n, rays_per_block):
            r1 = min(n, r0 + rays_per_block)
            ob, db = o[r0:r1, None, :], d[r0:r1, None, :]
            for f0 in range(0, nf, tris_per_block):
                f1 = min(nf, f0 + tris_per_block)
                e1, e2, v0 = self._e1[f0:f1], self._e2[f0:f1], self._v0[f0:f1]
                pvec = np.cross(db, e2[None])
                det = np.einsum("rfk,fk->rf", pvec, e1)
                ok = np.abs(det) > 1e-14
                inv = 1.0 / np.where(ok, det, 1.0)
                tvec = ob - v0[None]
                u = np.einsum("rfk,rfk->rf", tvec, pvec) * inv
                qvec = np.cross(tvec, e1[None])
                v = np.einsum("rk,rfk->rf", d[r0:r1], qvec) * inv
                t = np.einsum("fk,rfk->rf", e2, qvec) * inv
                good = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > tmin)
                if not first:
                    count[r0:r1] += good.sum(axis=1)
                    continue
                tt = np.where(good, t, np.inf)
                j = np.argmin(tt, axis=1)
                tj = tt[np.arange(r1 - r0), j]
                better = tj < best[r0:r1]
                best[r0:r1] = np.where(better, tj, best[r0:r1])
                face[r0:r1] = np.where(better, j + f0, face[r0:r1])
        return best, face, count

    def intersect(self, o, d, tmin: float = TMIN):
        o, d = _as_rays(o, d)
        t = np.full(o.shape[0], np.inf)
        face = np.full(o.shape[0], -1, dtype=np.int64)
        sel = np.nonzero(slab_any(o, d, self._lo - 1e-9, self._hi + 1e-9))[0]
        if sel.size:
            ts, fs, _ = self._mt(np.ascontiguousarray(o[sel]), np.ascontiguousarray(d[sel]), tmin)
            t[sel], face[sel] = ts, fs
        return t, face

    def normal(self, p, d=None, aux=None):
        n = self._fn[np.asarray(aux)]
        if d is not None:
            flip = np.einsum("ij,ij->i", n, d) > 0
            n = np.where(flip[:, None], -n, n)
        return n

    def contains(self, p):
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        inside_box = np.all((p >= self._lo) & (p <= self._hi), axis=1)
        out = np.zeros(p.shape[0], dtype=bool)
        idx = np.nonzero(inside_box)[0]
        if idx.size:
            d = np.broadcast_to(np.array([0.5773502691896258, 0.5773502691896257,
                                          0.5773502691896259]), (idx.size, 3))
            _, _, count = self._mt(p[idx], np.ascontiguousarray(d), 0.0, first=False)
            out[idx] = count % 2 == 1
        return out


def load_mesh(path, scale=1.0, source: str | None = None) -> Mesh:
    """Read an OBJ / PLY / GLB / STL (anything trimesh reads) into a Mesh (metres)."""
    where = source or str(path)
    try:
        import trimesh
    except ImportError:
        raise InputError(f"{where}: loading meshes needs the 'trimesh' package "
                         "(pip install trimesh)") from None
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:           # trimesh raises many types for broken files
        raise InputError(f"{where}: cannot read mesh {path}: {exc}") from None
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    f = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    if v.size == 0 or f.size == 0:
        raise InputError(f"{where}: mesh {path} is empty (no triangles)")
    return Mesh(v * np.asarray(scale, dtype=np.float64), f, source=f"{where} ({path})")
