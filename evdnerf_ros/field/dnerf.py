"""``dnerf``: the paper's backbone (a modified D-NeRF), to compare against.

- Deformation MLP (``depth`` x ``width``, skip connection re-injecting the input after
  layer ``skip``) on [PE(x, ``pe_x``), PE(t, ``pe_t``)] -> dx (3,).
- Canonical MLP (same shape) on PE(x + dx, ``pe_x``) -> density and one grey channel
  (sigmoid).  Paper sizes: 8 x 256, skip at 4, 10 frequencies each (the defaults).
- As in D-NeRF, t = 0 is the canonical time: dx is forced to 0 there
  (``zero_deform_at_t0``).
- Density activation: ``softplus`` by default (a non-negative density per metre);
  the notes record the public code as using a sigmoid density; ``"sigmoid"`` and ``"relu"``
  (original D-NeRF) are available.

No factorisation, so the static-view reuse is the generic fallback (two full evaluations).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .base import DynamicField


def positional_encoding(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """[x, sin(2^k pi x), cos(2^k pi x)] for k < n_freqs; (N, D) -> (N, D (1 + 2 n))."""
    if n_freqs <= 0:
        return x
    freqs = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * torch.pi
    xf = x.unsqueeze(-1) * freqs                     # (N, D, n)
    return torch.cat([x, torch.sin(xf).flatten(1), torch.cos(xf).flatten(1)], dim=1)


class _SkipMLP(nn.Module):
    def __init__(self, d_in: int, depth: int, width: int, skip: int | None):
        super().__init__()
        self.skip = skip
        layers = []
        d = d_in
        for i in range(depth):
            if skip is not None and i == skip + 1:
                d += d_in
            layers.append(nn.Linear(d, width))
            d = width
        self.layers = nn.ModuleList(layers)

    def forward(self, h0: torch.Tensor) -> torch.Tensor:
        h = h0
        for i, layer in enumerate(self.layers):
            if self.skip is not None and i == self.skip + 1:
                h = torch.cat([h0, h], dim=1)
            h = F.relu(layer(h))
        return h


class DNeRFField(DynamicField):
    def __init__(self, depth: int = 8, width: int = 256, skip: int | None = 4,
                 pe_x: int = 10, pe_t: int = 10, canonical_depth: int | None = None,
                 canonical_width: int | None = None, density_activation: str = "softplus",
                 zero_deform_at_t0: bool = True):
        super().__init__()
        if density_activation not in ("softplus", "sigmoid", "relu"):
            raise ValueError(f"unknown density_activation {density_activation!r}")
        self.pe_x, self.pe_t = int(pe_x), int(pe_t)
        self.density_activation = density_activation
        self.zero_deform_at_t0 = bool(zero_deform_at_t0)
        dx_in = 3 * (1 + 2 * self.pe_x)
        dt_in = 1 * (1 + 2 * self.pe_t)
        cd = depth if canonical_depth is None else canonical_depth
        cw = width if canonical_width is None else canonical_width
        sk = skip if skip is not None and skip < depth - 1 else None
        csk = skip if skip is not None and skip < cd - 1 else None
        self.deform = _SkipMLP(dx_in + dt_in, depth, width, sk)
        self.deform_out = nn.Linear(width, 3)
        self.canonical = _SkipMLP(dx_in, cd, cw, csk)
        self.density_out = nn.Linear(cw, 1)
        self.grey_out = nn.Linear(cw, 1)

    def deformation(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        h = torch.cat([positional_encoding(x, self.pe_x), positional_encoding(t, self.pe_t)],
                      dim=1)
        dx = self.deform_out(self.deform(h))
        if self.zero_deform_at_t0:
            dx = torch.where(t == 0, torch.zeros_like(dx), dx)
        return dx

    def forward(self, x: torch.Tensor, t: torch.Tensor):
        x = x.to(torch.float32)
        t = t.to(torch.float32).reshape(-1, 1).expand(x.shape[0], 1)
        return self.canonical_field(x + self.deformation(x, t))

    def decode_static(self, features):
        """No deformation: the canonical field at the point itself."""
        return self.canonical_field(features.to(torch.float32))

    def canonical_field(self, xc: torch.Tensor):
        h = self.canonical(positional_encoding(xc, self.pe_x))
        raw = self.density_out(h)[:, 0]
        if self.density_activation == "softplus":
            density = F.softplus(raw)
        elif self.density_activation == "sigmoid":
            density = torch.sigmoid(raw)
        else:
            density = F.relu(raw)
        grey = torch.sigmoid(self.grey_out(h)[:, 0])
        return density, grey
