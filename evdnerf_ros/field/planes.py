"""``planes``: a K-Planes / HexPlane-style factorised 4D field in plain PyTorch.

Per scale s (space resolution R_s, time resolution T):
- 3 space planes  (xy, xz, yz), each (F, R_s, R_s), initialised uniform(a, b);
- 3 space-time planes (xt, yt, zt), each (F, T, R_s), initialised to **1**, so a point
  is static until the data says otherwise (and the field is independent of t at init).
Features are bilinear ``grid_sample`` lookups (``align_corners=True``: -1 and +1 are the
outermost texel centres), multiplied (Hadamard product) across the six planes, and
concatenated across scales.  A tiny MLP decodes density (softplus or truncated exp) and
grey (sigmoid).  No view dependence.

Static-view reuse: ``space_features`` returns the product of the three space planes per
scale; ``decode`` multiplies in the three time planes and runs the MLP; ``decode_static``
runs the MLP on the space product alone (time factors 1).  When every point is at one time
(a training batch's window edge, a published frame) ``decode`` blends each time plane to
that time's row once and reads it at the points' columns (``decode_at``): the same values
and gradients as the bilinear lookups (to float rounding), 1D gathers instead of 2D lookups.
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from .base import DynamicField

_SPACE_PAIRS = ((0, 1), (0, 2), (1, 2))     # xy, xz, yz   (grid x = first, grid y = second)


class _TruncExp(torch.autograd.Function):
    """exp with the gradient clamped (Instant-NGP / K-Planes' density activation)."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(-15.0, 15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return _TruncExp.apply(x.clamp(max=15.0))


def decoder_mlp(inputs: int, hidden: int, hidden_layers: int, gen: torch.Generator | None) -> nn.Sequential:
    """The tiny decoder: ``hidden_layers`` x (Linear, ReLU), then Linear to (density, grey) logits;
    with ``gen``, initialised from it (PyTorch's default uniform bounds) for a seeded field."""
    layers: list[nn.Module] = []
    d = int(inputs)
    for _ in range(int(hidden_layers)):
        layers += [nn.Linear(d, hidden), nn.ReLU()]
        d = hidden
    layers.append(nn.Linear(d, 2))
    decoder = nn.Sequential(*layers)
    if gen is not None:
        with torch.no_grad():
            for m in decoder:
                if isinstance(m, nn.Linear):
                    bound = 1.0 / m.in_features ** 0.5
                    m.weight.uniform_(-bound, bound, generator=gen)
                    m.bias.uniform_(-bound, bound, generator=gen)
    return decoder


def activate(raw: torch.Tensor, density_activation: str, density_bias: float):
    """Decoder logits (N, 2) -> (density (N,) >= 0, grey (N,) in (0, 1))."""
    logit = raw[:, 0] + density_bias
    density = F.softplus(logit) if density_activation == "softplus" else trunc_exp(logit)
    return density, torch.sigmoid(raw[:, 1])


class PlanesField(DynamicField):
    reuses_space_features = True

    def __init__(self, resolutions: Sequence[int] = (16, 32, 64), time_resolution: int = 16,
                 features: int = 16, hidden: int = 64, hidden_layers: int = 1,
                 density_activation: str = "softplus", density_bias: float = -1.0,
                 init_range: tuple = (0.1, 0.5), seed: int | None = None):
        super().__init__()
        if density_activation not in ("softplus", "trunc_exp"):
            raise ValueError(f"density_activation must be softplus or trunc_exp, "
                             f"got {density_activation!r}")
        self.resolutions = tuple(int(r) for r in resolutions)
        self.time_resolution = int(time_resolution)
        self.features = int(features)
        self.density_activation = density_activation
        self.density_bias = float(density_bias)
        gen = torch.Generator().manual_seed(seed) if seed is not None else None
        a, b = init_range
        self.space_planes = nn.ParameterList()
        self.time_planes = nn.ParameterList()
        for r in self.resolutions:
            sp = torch.rand(3, self.features, r, r, generator=gen) * (b - a) + a
            self.space_planes.append(nn.Parameter(sp))
            # rows = time, columns = the space axis
            self.time_planes.append(nn.Parameter(
                torch.ones(3, self.features, self.time_resolution, r)))
        self.decoder = decoder_mlp(self.features * len(self.resolutions), hidden, hidden_layers, gen)

    @staticmethod
    def _lookup(planes: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """planes (3, F, H, W), coords (3, N, 2) in [-1, 1] -> (3, N, F)."""
        out = F.grid_sample(planes, coords.unsqueeze(2), mode="bilinear",
                            padding_mode="border", align_corners=True)   # (3, F, N, 1)
        return out.squeeze(-1).transpose(1, 2)

    def space_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = x.to(torch.float32)
        coords = torch.stack([x[:, [i, j]] for i, j in _SPACE_PAIRS])       # (3, N, 2)
        feats = []
        for planes in self.space_planes:
            f = self._lookup(planes, coords)
            feats.append(f[0] * f[1] * f[2])
        return [x, feats]

    def decode(self, features, t: torch.Tensor):
        t = t.to(torch.float32)
        if features[0].shape[0] and bool((t == t.reshape(-1)[0]).all()):
            # every point at one time (a training batch's window edge): each time plane is
            # blended to that time's row once and read at 1D columns, not looked up in 2D
            return self.decode_at(self.playback_features(features), float(t.reshape(-1)[0]))
        return self.decode_per_point(features, t)

    def decode_per_point(self, features, t: torch.Tensor):
        """``decode`` with bilinear lookups of the time planes at each point's own time."""
        x, feats = features
        n = x.shape[0]
        tt = (t.to(torch.float32).reshape(-1, 1).expand(n, 1)) * 2.0 - 1.0
        # grid x = space coordinate (columns), grid y = time (rows)
        coords = torch.stack([torch.cat([x[:, i:i + 1], tt], dim=1) for i in range(3)])
        out = []
        for planes, sf in zip(self.time_planes, feats):
            f = self._lookup(planes, coords)
            out.append(sf * (f[0] * f[1] * f[2]))
        return self._head(torch.cat(out, dim=1))

    # ----- playback at one time for many points (the publisher's renderer)
    def playback_features(self, features):
        """``space_features(x)`` plus, per scale and space axis, the two columns of the time
        planes each point falls between and its weight: what ``decode_at`` needs, fixed while
        the points are (a static camera's samples)."""
        x, feats = features
        columns = []
        for planes in self.time_planes:
            r = planes.shape[-1]
            u = (x.clamp(-1.0, 1.0) + 1.0) * (0.5 * (r - 1))               # (N, 3) in [0, r - 1]
            j0 = u.floor().clamp(0, max(r - 2, 0)).long()
            columns.append((j0.T.contiguous(), (j0 + 1).clamp(max=r - 1).T.contiguous(),
                            (u - j0).T.contiguous().unsqueeze(-1)))
        return [x, feats, columns]

    def decode_at(self, playback, t: float):
        """``decode`` of every point at one normalised time ``t`` (equal to float rounding):
        each time plane is first blended to its row at ``t`` (F x R), then read at the points'
        precomputed columns, two row gathers per axis instead of a bilinear lookup."""
        x, feats, columns = playback
        rows = self.time_resolution - 1
        ti = min(max(float(t), 0.0), 1.0) * rows
        i0 = min(int(ti), max(rows - 1, 0))
        i1 = min(i0 + 1, rows)
        w = ti - i0
        out = []
        for planes, sf, (j0, j1, a) in zip(self.time_planes, feats, columns):
            # (3, R, F), contiguous: row gathers by index_select are 1.5x faster than indexing the
            # transposed view (the same values)
            row = (planes[:, :, i0, :] * (1.0 - w) + planes[:, :, i1, :] * w).transpose(1, 2).contiguous()
            prod = sf
            for i in range(3):
                prod = prod * torch.lerp(row[i].index_select(0, j0[i]), row[i].index_select(0, j1[i]), a[i])
            out.append(prod)
        return self._head(torch.cat(out, dim=1))

    def decode_static(self, features):
        """Time factors taken as 1 (the planes' initial value: a point that never changes)."""
        return self._head(torch.cat(features[1], dim=1))

    def _head(self, feat: torch.Tensor):
        return activate(self.decoder(feat), self.density_activation, self.density_bias)

    def forward(self, x: torch.Tensor, t: torch.Tensor):
        return self.decode(self.space_features(x), t)
