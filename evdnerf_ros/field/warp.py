"""``warp``: a static canonical field seen through a time-dependent warp (D-NeRF's idea on
K-Planes' grids).

A product of planes (``planes``) changes a point's features over time but cannot move
them: an object that translates by its own length leaves a trail of features that must
appear and vanish in step, which products of 2D planes represent badly (the jet of
Jet-Down crosses the image in one second).  Here the scene is one static field, the
canonical space, and time only moves where each point looks into it:

    x_c = x + offset(x, t),   (density, grey) = canonical(x_c)

- ``canonical``: a static multi-scale triplane (``PlanesField`` with no time planes) and
  its MLP.
- ``offset``: three additive space-time planes (xt, yt, zt), each (3, T, R): offset(x, t)
  = A_xt(x, t) + A_yt(y, t) + A_zt(z, t), bilinear, initialised to 0 (the field starts
  static).  A translation is constant along space, a small rotation is linear in the
  coordinates (each offset component varies with one coordinate per rotation axis), and
  the sum needs no decoder, so every gradient reaches the planes at once.

Static points (``decode_static``) are the canonical field at the point itself (no warp).
Time enters only through the warp, so the static-view reuse is the generic one: the
canonical lookups are repeated at each time (they move with it); the offset's lookups are
the time-dependent part and cost a third of the canonical's.
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from .planes import PlanesField


class WarpField(PlanesField):
    reuses_space_features = False

    def __init__(self, resolutions: Sequence[int] = (16, 32, 64), features: int = 16,
                 hidden: int = 64, hidden_layers: int = 1, density_activation: str = "softplus",
                 density_bias: float = -1.0, init_range: tuple = (0.1, 0.5),
                 warp_resolution: int = 16, warp_time_resolution: int = 32,
                 seed: int | None = None):
        super().__init__(resolutions=resolutions, time_resolution=0, features=features,
                         hidden=hidden, hidden_layers=hidden_layers,
                         density_activation=density_activation, density_bias=density_bias,
                         init_range=init_range, seed=seed)
        self.warp_resolution = int(warp_resolution)
        self.warp_time_resolution = int(warp_time_resolution)
        self.time_resolution = self.warp_time_resolution      # time texels (what baking samples)
        # rows = time, columns = the space axis; 3 channels = the offset's x, y, z
        self.warp_planes = nn.Parameter(torch.zeros(3, 3, self.warp_time_resolution,
                                                    self.warp_resolution))

    def offset(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(N, 3) normalised points, (N, 1) times in [0, 1] -> (N, 3) offsets into the
        canonical space (normalised units)."""
        tt = t.to(torch.float32).reshape(-1, 1).expand(x.shape[0], 1) * 2.0 - 1.0
        coords = torch.stack([torch.cat([x[:, i:i + 1], tt], dim=1) for i in range(3)])
        out = F.grid_sample(self.warp_planes, coords.unsqueeze(2), mode="bilinear",
                            padding_mode="border", align_corners=True)      # (3 planes, 3, N, 1)
        return out.sum(dim=0).squeeze(-1).transpose(0, 1)

    def space_features(self, x: torch.Tensor):
        return x.to(torch.float32)

    def decode(self, features, t: torch.Tensor):
        x = features
        warped = (x + self.offset(x, t)).clamp(-1.0, 1.0)
        return self.decode_static(super().space_features(warped))

    def decode_static(self, features):
        if isinstance(features, torch.Tensor):          # a point, as space_features gives it
            features = super().space_features(features)
        return super().decode_static(features)

    def forward(self, x: torch.Tensor, t: torch.Tensor):
        return self.decode(self.space_features(x), t)
