"""``hinge``: a scene of one rigid part turning on a known joint, in front of a static world.

The rig knows its joint: the servo's axis and pivot (rig geometry) and its angle over time (the
firmware's motion profile). So the field need not learn *how* things move, only *what* moves:

- a static triplane (world coordinates) for everything that never moves;
- a moving triplane in the part's own frame (the joint at angle 0): a world point ``x`` at time
  ``t`` is looked up at ``pivot + R(axis, -angle(t)) (x - pivot)``.

density = static + moving; grey = their density-weighted mean. Each triplane is the product of
three bilinear plane lookups per scale (``PlanesField``'s space part), concatenated across
scales, decoded by its own small MLP (the moving part's also gets cos and sin of the joint
angle, ``shading``: a face turning towards or away from a light changes its grey). Every time shares one shape, so an event at any moment of
the swing teaches the part's shape for all moments (a ``planes`` field learns one shape per time
row, each seen only by the few views that saw that row's moments).

``joint`` (plain data, saved with the config): ``pivot`` (3, box-normalised), ``axis`` (3, world,
unit), ``half`` (3, the box's half extents in metres: the rotation is rigid in metres, not in
normalised units) and ``angles_rad`` (K >= 2 samples of the angle over normalised time 0..1,
linear between them). ``train.joint`` derives it from a training set's true scene.

``decode_static`` is the static triplane alone: outside the dynamic region (where the trainer
and the renderers call it) the moving part never is. ``static_time_resolution`` > 0 makes the
world a ``planes`` field with that many time rows (static until the data says otherwise), for
what the part does to it: the shadow it casts.
"""

from __future__ import annotations

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


class HingeField(DynamicField):
    reuses_space_features = True

    def __init__(self, joint: dict, resolutions: Sequence[int] = (16, 32, 64), features: int = 16,
                 hidden: int = 64, hidden_layers: int = 1, density_activation: str = "softplus",
                 density_bias: float = -1.0, init_range: tuple = (0.1, 0.5), seed: int | None = None,
                 shading: bool = True, static_time_resolution: int = 0):
        super().__init__()
        if density_activation not in ("softplus", "trunc_exp"):
            raise ValueError(f"density_activation must be softplus or trunc_exp, got {density_activation!r}")
        for key in ("pivot", "axis", "half", "angles_rad"):
            if key not in joint:
                raise ValueError(f"hinge field: joint has no {key!r} (keys: {sorted(joint)})")
        angles = torch.as_tensor(joint["angles_rad"], dtype=torch.float32).reshape(-1)
        if angles.numel() < 2 or not bool(torch.isfinite(angles).all()):
            raise ValueError("hinge field: joint.angles_rad needs >= 2 finite samples")
        axis = torch.as_tensor(joint["axis"], dtype=torch.float32).reshape(3)
        if not float(axis.norm()) > 0:
            raise ValueError("hinge field: joint.axis must be a non-zero vector")
        half = torch.as_tensor(joint["half"], dtype=torch.float32).reshape(3)
        if not bool((half > 0).all()):
            raise ValueError("hinge field: joint.half must be > 0 on every axis")
        self.density_activation = density_activation
        self.density_bias = float(density_bias)
        self.register_buffer("pivot", torch.as_tensor(joint["pivot"], dtype=torch.float32).reshape(3))
        self.register_buffer("axis", axis / axis.norm())
        self.register_buffer("half_extent", half)
        self.register_buffer("angles", angles)
        gen = torch.Generator().manual_seed(seed) if seed is not None else None
        self.static_time_resolution = int(static_time_resolution)
        if self.static_time_resolution > 0:
            # the world may change too (the shadow the part casts): a planes field, static until
            # the data says otherwise
            self.static = PlanesField(resolutions, self.static_time_resolution, features, hidden, hidden_layers,
                                      density_activation, density_bias, init_range, seed)
        else:
            self.static = Triplane(resolutions, features, hidden, hidden_layers, init_range, gen)
        self.shading = bool(shading)
        self.moving = Triplane(resolutions, features, hidden, hidden_layers, init_range, gen,
                               extra_inputs=2 if self.shading else 0)

    def angle(self, t: torch.Tensor) -> torch.Tensor:
        """The joint angle (radians) at normalised times ``t`` (any shape), linear between samples."""
        u = t.to(torch.float32).clamp(0.0, 1.0) * (self.angles.numel() - 1)
        i0 = u.floor().long().clamp(max=self.angles.numel() - 2)
        return torch.lerp(self.angles[i0], self.angles[i0 + 1], u - i0)

    def part_frame(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Box-normalised world points -> the moving part's frame (rotated by -angle(t) about
        the joint, in metres), box-normalised again."""
        w = (x - self.pivot) * self.half_extent
        theta = -self.angle(t.reshape(-1))
        c, s = torch.cos(theta).unsqueeze(1), torch.sin(theta).unsqueeze(1)
        k = self.axis.expand_as(w)
        # Rodrigues: w cos + (k x w) sin + k (k . w)(1 - cos)
        rotated = w * c + torch.cross(k, w, dim=1) * s + k * (w @ self.axis).unsqueeze(1) * (1.0 - c)
        return rotated / self.half_extent + self.pivot

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
        theta = self.angle(t)
        cs = torch.stack([torch.cos(theta), torch.sin(theta)], dim=1) if self.shading else None
        dm, gm = self._activate(self.moving(self.part_frame(x, t).clamp(-1.0, 1.0), cs))
        density = ds + dm
        grey = (ds * gs + dm * gm) / density.clamp_min(1e-8)
        return density, grey

    def decode_static(self, features):
        return self.static.decode_static(features[1]) if self.static_time_resolution else features[1]

    def forward(self, x: torch.Tensor, t: torch.Tensor):
        return self.decode(self.space_features(x), t)
