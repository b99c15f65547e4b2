"""Pinhole cameras, the camera ring of the rig, and pixel ray generation.

Conventions (DESIGN.md): ``T_world_cam`` is a 4x4 float64 matrix mapping camera
coordinates to world coordinates, camera axes OpenCV (x right, y down, z forward).
The world is z-up (as in the paper's Blender scenes).

Pixel coordinates follow OpenCV: pixel (u, v) has its centre at integer (u, v), the image
spans [-0.5, W - 0.5] x [-0.5, H - 0.5], and ``from_fov`` puts the principal point at the
image centre ``((W - 1) / 2, (H - 1) / 2)`` with ``fx = fy = (W / 2) / tan(fov_x / 2)``
(``fov_deg`` is the horizontal field of view, the paper's ``camera_angle_x``).

Camera ring: view k of N sits at azimuth ``offset_deg + 360 k / N`` (measured in the
world xy plane from +x towards +y), at ``elevation_deg`` above the look-at point's
horizontal plane, ``radius`` metres from it; its optical axis passes through the look-at
point and its x axis is horizontal (no roll).  Validation views are the same ring rotated
by ``validation_offset_deg`` (the paper: 18 views 20 deg apart, validation offset 10 deg).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

WORLD_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics (pixels); no distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        if int(self.width) < 1 or int(self.height) < 1:
            raise InputError(f"camera size must be positive, got {self.width}x{self.height}")
        for name in ("fx", "fy", "cx", "cy"):
            if not np.isfinite(getattr(self, name)):
                raise InputError(f"camera {name} must be finite")
        if self.fx <= 0 or self.fy <= 0:
            raise InputError("camera focal lengths must be positive")

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float) -> "PinholeCamera":
        if not 0.0 < float(fov_deg) < 180.0:
            raise InputError(f"fov_deg must be in (0, 180), got {fov_deg}")
        f = float((width / 2.0) / np.tan(np.radians(fov_deg) / 2.0))
        return cls(int(width), int(height), f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def fov_x_deg(self) -> float:
        return float(np.degrees(2.0 * np.arctan(self.width / 2.0 / self.fx)))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def resized(self, width: int, height: int) -> "PinholeCamera":
        """Same field of view at another resolution (intrinsics scaled with the image)."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(int(width), int(height), self.fx * sx, self.fy * sy,
                             (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N, 2) pixel coordinates (u, v)."""
        p = np.asarray(points_cam, dtype=np.float64)
        return np.stack([self.fx * p[:, 0] / p[:, 2] + self.cx,
                         self.fy * p[:, 1] / p[:, 2] + self.cy], axis=1)

    def ray_directions(self, supersample: int = 1) -> np.ndarray:
        """Unit ray directions in the camera frame, shape (H*s, W*s, 3) float64.

        With supersampling ``s`` pixel (u, v) is covered by the s x s grid of sub-pixel
        centres ``u - 0.5 + (i + 0.5) / s``; row ``v*s + j``, column ``u*s + i``.
        """
        s = int(supersample)
        if s < 1:
            raise InputError(f"supersample must be >= 1, got {supersample}")
        off = (np.arange(s) + 0.5) / s - 0.5
        u = (np.arange(self.width)[:, None] + off[None, :]).ravel()
        v = (np.arange(self.height)[:, None] + off[None, :]).ravel()
        x = (u - self.cx) / self.fx
        y = (v - self.cy) / self.fy
        d = np.empty((v.size, u.size, 3))
        d[..., 0] = x[None, :]
        d[..., 1] = y[:, None]
        d[..., 2] = 1.0
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return d


def look_at(position, target, up=WORLD_UP) -> np.ndarray:
    """T_world_cam of a camera at ``position`` whose optical axis passes through ``target``."""
    p = np.asarray(position, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - p
    n = np.linalg.norm(z)
    if n == 0:
        raise InputError("camera position equals its look-at point")
    z /= n
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise InputError("camera looks straight along the up axis; its roll is undefined "
                         "(use |elevation_deg| < 89)")
    x /= nx
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, p
    return T


def common_look_at(poses) -> np.ndarray:
    """(3,) the point nearest to the optical axes (+z, OpenCV) of the (K, 4, 4) T_world_cam ``poses``,
    least squares: where a ring of views looks; their centres' mean where the axes do not fix one."""
    poses = np.asarray(poses, np.float64)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, z in zip(poses[:, :3, 3], poses[:, :3, 2]):
        d = z / np.linalg.norm(z)
        P = np.eye(3) - np.outer(d, d)          # removes the component along the axis
        A += P
        b += P @ c
    try:
        return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return poses[:, :3, 3].mean(axis=0)


def ring_poses(views: int, radius: float, elevation_deg: float, look_at_point=(0, 0, 0),
               offset_deg: float = 0.0) -> list[np.ndarray]:
    """T_world_cam of ``views`` cameras evenly spaced on a ring (see module docstring)."""
    if int(views) < 1:
        raise InputError(f"a camera ring needs at least one view, got {views}")
    if not radius > 0:
        raise InputError(f"camera ring radius must be positive, got {radius}")
    if not abs(elevation_deg) < 89.0:
        raise InputError(f"elevation_deg must be within (-89, 89), got {elevation_deg}")
    c = np.asarray(look_at_point, dtype=np.float64)
    el = np.radians(elevation_deg)
    poses = []
    for k in range(int(views)):
        az = np.radians(offset_deg + 360.0 * k / views)
        pos = c + radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                     np.sin(el)])
        poses.append(look_at(pos, c))
    return poses


@dataclass(frozen=True)
class CameraRing:
    views: int = 18
    radius: float = 4.0
    elevation_deg: float = 20.0
    look_at: tuple = (0.0, 0.0, 0.0)
    offset_deg: float = 0.0
    validation_offset_deg: float = 10.0
    validation_views: int | None = None        # default: as many as training views

    def poses(self, split: str = "train", views: int | None = None) -> list[np.ndarray]:
        """Poses of the ``train`` or ``val`` ring (optionally another number of views)."""
        if split not in ("train", "val"):
            raise InputError(f"camera split must be 'train' or 'val', got {split!r}")
        n = views if views is not None else (
            self.views if split == "train" else (self.validation_views or self.views))
        off = self.offset_deg + (self.validation_offset_deg if split == "val" else 0.0)
        return ring_poses(n, self.radius, self.elevation_deg, self.look_at, off)

    def pose_at(self, azimuth_deg: float) -> np.ndarray:
        """T_world_cam of a camera on this ring at ``azimuth_deg``."""
        return ring_poses(1, self.radius, self.elevation_deg, self.look_at, float(azimuth_deg))[0]

    def azimuths_deg(self, split: str = "train", views: int | None = None) -> list[float]:
        n = views if views is not None else (
            self.views if split == "train" else (self.validation_views or self.views))
        off = self.offset_deg + (self.validation_offset_deg if split == "val" else 0.0)
        return [off + 360.0 * k / n for k in range(n)]


@dataclass(frozen=True)
class CameraSetup:
    ring: CameraRing = field(default_factory=CameraRing)
    intrinsics: PinholeCamera = field(
        default_factory=lambda: PinholeCamera.from_fov(256, 256, 40.0))
    fov_deg: float = 40.0
