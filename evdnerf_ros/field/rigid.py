"""``rigid``: a scene of one rigid part moving freely in front of a static world, its pose learned.

Where no rig records the motion (a part thrown, flown or carried: Jet-Down, Jet-Spiral, Jet-Land
are rigid), the field learns the part's pose over time together with its shape: a static world and
one rigid part (``part.PartField``), a world point ``x`` at time ``t`` being looked up at
``R(r(t))^T (x - c(t)) / radius`` (metres; the part's own triplane spans only the ball the part
fits in, so its cells are finer than the scene box's for the same cost). ``c(t)`` and the
rotation vector ``r(t)`` are learned at ``K`` knots over normalised time 0..1, linear between them;
``c`` starts at ``track.centre``, the centroid of the per-time visual hulls of the events
(``train.track``), ``r`` at zero. The part's decoder also reads ``r(t)`` (``shading``). The poses
learn at ``pose_lr_scale`` times the field's learning rate (Adam moves every parameter by about
the learning rate per step: a pose at the full rate jitters by centimetres).

``track`` (plain data, saved with the config): ``centre`` (K >= 2 rows of 3, box-normalised),
``half`` (3, the box's half extents in metres) and ``radius`` (metres: how far the part reaches
from its centre; beyond it the part's triplane reads its border, which learns to be empty).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from .part import PartField, lerp_table


def rotate(w: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """(N, 3) vectors rotated by (N, 3) rotation vectors (Rodrigues, smooth at r = 0)."""
    theta = torch.sqrt((r * r).sum(1, keepdim=True) + 1e-12)
    a = torch.sin(theta) / theta
    half = 0.5 * theta
    b = 0.5 * (torch.sin(half) / half) ** 2        # (1 - cos theta) / theta^2 without cancellation
    rw = torch.cross(r, w, dim=1)
    return w + a * rw + b * torch.cross(r, rw, dim=1)


class RigidField(PartField):
    def __init__(self, track: dict, resolutions: Sequence[int] = (16, 32, 64), features: int = 16,
                 hidden: int = 64, hidden_layers: int = 1, density_activation: str = "softplus",
                 density_bias: float = -1.0, init_range: tuple = (0.1, 0.5), seed: int | None = None,
                 shading: bool = True, static_time_resolution: int = 0, pose_lr_scale: float = 0.1):
        for key in ("centre", "half", "radius"):
            if key not in track:
                raise ValueError(f"rigid field: track has no {key!r} (keys: {sorted(track)})")
        centre = torch.as_tensor(track["centre"], dtype=torch.float32)
        if centre.dim() != 2 or centre.shape[1] != 3 or centre.shape[0] < 2 or not bool(torch.isfinite(centre).all()):
            raise ValueError(f"rigid field: track.centre needs >= 2 finite rows of 3, got shape {tuple(centre.shape)}")
        half = torch.as_tensor(track["half"], dtype=torch.float32).reshape(3)
        if not bool((half > 0).all()):
            raise ValueError("rigid field: track.half must be > 0 on every axis")
        if not float(track["radius"]) > 0:
            raise ValueError(f"rigid field: track.radius must be > 0, got {track['radius']}")
        if not pose_lr_scale >= 0:
            raise ValueError(f"rigid field: pose_lr_scale must be >= 0, got {pose_lr_scale}")
        self.shading = bool(shading)
        super().__init__(resolutions, features, hidden, hidden_layers, density_activation, density_bias,
                         init_range, seed, static_time_resolution, 3 if self.shading else 0)
        self.pose_lr_scale = float(pose_lr_scale)
        self.register_buffer("half_extent", half)
        self.register_buffer("radius", torch.tensor(float(track["radius"])))
        self.centre = nn.Parameter(centre.clone())
        self.rotation = nn.Parameter(torch.zeros_like(centre))

    def pose(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(centre (N, 3) box-normalised, rotation vector (N, 3)) at normalised times (N,)."""
        return lerp_table(self.centre, t), lerp_table(self.rotation, t)

    def part_frame(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        c, r = self.pose(t.reshape(-1))
        w = (x - c) * self.half_extent
        return rotate(w, -r) / self.radius

    def part_inputs(self, t: torch.Tensor) -> torch.Tensor | None:
        return lerp_table(self.rotation, t) if self.shading else None

    def param_groups(self) -> list[tuple[list, float]]:
        poses = [self.centre, self.rotation]
        rest = [p for p in self.parameters() if all(p is not q for q in poses)]
        return [(rest, 1.0), (poses, self.pose_lr_scale)]
