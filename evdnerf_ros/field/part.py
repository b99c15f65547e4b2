"""A static world and one rigid moving part: what the ``hinge`` and ``rigid`` fields share.

- a static triplane (world coordinates) for everything that never moves;
- a moving triplane in the part's own frame: a world point ``x`` at time ``t`` is looked up at
  ``part_frame(x, t)`` (a subclass says where the part is at ``t``: ``hinge`` from the rig's
  joint, ``rigid`` from a learned pose track).

density = static + moving; grey = their density-weighted mean. Each triplane is the product of
three bilinear plane lookups per scale (``PlanesField``'s space part), concatenated across
scales, decoded by its own small MLP (the moving part's also reads ``part_inputs(t)``, its pose:
a face turning towards or away from a light changes its grey). Every time shares one shape, so
an event at any moment teaches the part's shape for all moments (a ``planes`` field learns one
shape per time row, each seen only by the few views that saw that row's moments).

``decode_static`` is the static triplane alone: outside the dynamic region (where the trainer
and the renderers call it) the moving part never is. ``static_time_resolution`` > 0 makes the
world a ``planes`` field with that many time rows (static until the data says otherwise), for
what the part does to it: the shadow it casts.
"""

from __future__ import annotations

import abc
from typing import Sequence

import torch
from torch import nn

from .base import DynamicField
from .planes import _SPACE_PAIRS, PlanesField, activate, decoder_mlp


class Triplane(nn.Module):
    """Static (time-free) space planes per scale + an MLP head -> (density, grey)."""

    def __init__(self, resolutions: Sequence[int], features: int, hidden: int, hidden_layers: int,
                 init_range: tuple, gen: torch.Generator | None, extra_inputs: int = 0):
        super().__init__()
        a, b = init_range
        self.planes = nn.ParameterList(
            nn.Parameter(torch.rand(3, features, int(r), int(r), generator=gen) * (b - a) + a)
            for r in resolutions)
        self.decoder = decoder_mlp(features * len(self.planes) + int(extra_inputs), hidden, hidden_layers, gen)

    def forward(self, x: torch.Tensor, extra: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 3) in [-1, 1] (and (N, extra_inputs) more decoder inputs) -> raw (N, 2): density
        logit and grey logit."""
        coords = torch.stack([x[:, [i, j]] for i, j in _SPACE_PAIRS])
        feats = []
        for planes in self.planes:
            f = PlanesField._lookup(planes, coords)
            feats.append(f[0] * f[1] * f[2])
        if extra is not None:
            feats.append(extra)
        return self.decoder(torch.cat(feats, dim=1))


class PartField(DynamicField, abc.ABC):
    """Static world + one rigid part (module notes); subclasses give ``part_frame`` and
    ``part_inputs`` (the ``part_input_count`` extra inputs of the part's decoder)."""

    reuses_space_features = True
    #: the part's frame spans only its own box, outside which it is empty (``hinge``'s part_box)
    part_bounded = False
    #: that box's volume over the scene box's (1: the part's frame spans the scene box)
    part_volume_fraction = 1.0

    def __init__(self, resolutions: Sequence[int], features: int, hidden: int, hidden_layers: int,
                 density_activation: str, density_bias: float, init_range: tuple, seed: int | None,
                 static_time_resolution: int, part_input_count: int):
        super().__init__()
        if density_activation not in ("softplus", "trunc_exp"):
            raise ValueError(f"density_activation must be softplus or trunc_exp, got {density_activation!r}")
        self.density_activation = density_activation
        self.density_bias = float(density_bias)
        gen = torch.Generator().manual_seed(seed) if seed is not None else None
        self.static_time_resolution = int(static_time_resolution)
        if self.static_time_resolution > 0:
            # the world may change too (the shadow the part casts): a planes field, static until
            # the data says otherwise
            self.static = PlanesField(resolutions, self.static_time_resolution, features, hidden, hidden_layers,
                                      density_activation, density_bias, init_range, seed)
        else:
            self.static = Triplane(resolutions, features, hidden, hidden_layers, init_range, gen)
        self.moving = Triplane(resolutions, features, hidden, hidden_layers, init_range, gen,
                               extra_inputs=part_input_count)

    @abc.abstractmethod
    def part_frame(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(N, 3) box-normalised world points at (N,) times -> the part's frame, box-normalised."""

    @abc.abstractmethod
    def part_inputs(self, t: torch.Tensor) -> torch.Tensor | None:
        """(N,) times -> (N, part_input_count) more inputs of the part's decoder (or None)."""

    def _activate(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return activate(raw, self.density_activation, self.density_bias)

    # ----- the reuse pair: the static triplane once per point, the moving one per time
    def space_features(self, x: torch.Tensor):
        x = x.to(torch.float32)
        if self.static_time_resolution:
            return x, self.static.space_features(x)
        return x, self._activate(self.static(x))

    def decode(self, features, t: torch.Tensor):
        x, static = features
        t = t.to(torch.float32).reshape(-1)
        if t.numel() == 1:
            t = t.expand(x.shape[0])
        ds, gs = self.static.decode(static, t) if self.static_time_resolution else static
        p = self.part_frame(x, t)
        dm, gm = self._activate(self.moving(p.clamp(-1.0, 1.0), self.part_inputs(t)))
        if self.part_bounded:          # the part is empty outside its own box
            dm = dm * (p.abs() <= 1.0).all(dim=1)
        density = ds + dm
        grey = (ds * gs + dm * gm) / density.clamp_min(1e-8)
        return density, grey

    def decode_static(self, features):
        return self.static.decode_static(features[1]) if self.static_time_resolution else features[1]

    def part_density(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(N,) density of the moving part alone at (N, 3) points of its own frame (box-normalised)
        at (N,) normalised times: what the trainer's ``part_empty_weight`` prior keeps sparse."""
        return self._activate(self.moving(x.to(torch.float32), self.part_inputs(t.to(torch.float32))))[0]

    def forward(self, x: torch.Tensor, t: torch.Tensor):
        return self.decode(self.space_features(x), t)


def lerp_table(table: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Rows of ``table`` (K >= 2, ...) at normalised times ``t`` (N,) in [0, 1] (clamped), linear
    between rows k / (K - 1)."""
    u = t.to(torch.float32).clamp(0.0, 1.0) * (table.shape[0] - 1)
    i0 = u.floor().long().clamp(max=table.shape[0] - 2)
    w = (u - i0).reshape(-1, *([1] * (table.dim() - 1)))
    return torch.lerp(table[i0], table[i0 + 1], w)
