"""``hinge``: a scene of one rigid part turning on a known joint, in front of a static world.

The rig knows its joint: the servo's axis and pivot (rig geometry) and its angle over time (the
firmware's motion profile). So the field need not learn *how* things move, only *what* moves: a
static world and one rigid part (``part.PartField``), the part's frame being the joint at angle
0: a world point ``x`` at time ``t`` is looked up at ``pivot + R(axis, -angle(t)) (x - pivot)``.
The part's decoder also reads cos and sin of the angle (``shading``).

``joint`` (plain data, saved with the config): ``pivot`` (3, box-normalised), ``axis`` (3, world,
unit), ``half`` (3, the box's half extents in metres: the rotation is rigid in metres, not in
normalised units) and ``angles_rad`` (K >= 2 samples of the angle over normalised time 0..1,
linear between them); optionally ``part_box`` ([[lo], [hi]], box-normalised, in the part's
frame): the part's planes span only that box and the part is empty outside it (``TrainConfig
.part_box``). ``train.joint`` derives them from a training set's joint record and dynamic region.
"""

from __future__ import annotations

from typing import Sequence

import torch

from .part import PartField, lerp_table


#: The space planes' resolutions per scale (static world and part alike) unless a config sets them.
RESOLUTIONS = (16, 32, 64)


class HingeField(PartField):
    def __init__(self, joint: dict, resolutions: Sequence[int] = RESOLUTIONS, features: int = 16,
                 hidden: int = 64, hidden_layers: int = 1, density_activation: str = "softplus",
                 density_bias: float = -1.0, init_range: tuple = (0.1, 0.5), seed: int | None = None,
                 shading: bool = True, static_time_resolution: int = 0):
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
        self.shading = bool(shading)
        super().__init__(resolutions, features, hidden, hidden_layers, density_activation, density_bias,
                         init_range, seed, static_time_resolution, 2 if self.shading else 0)
        self.register_buffer("pivot", torch.as_tensor(joint["pivot"], dtype=torch.float32).reshape(3))
        self.register_buffer("axis", axis / axis.norm())
        self.register_buffer("half_extent", half)
        self.register_buffer("angles", angles)
        box = joint.get("part_box")
        if box is not None:
            box = torch.as_tensor(box, dtype=torch.float32)
            if box.shape != (2, 3) or not bool(torch.isfinite(box).all()) or not bool((box[1] > box[0]).all()):
                raise ValueError(f"hinge field: joint.part_box must be [[lo x, y, z], [hi x, y, z]] with hi > lo, "
                                 f"got {joint['part_box']}")
            self.register_buffer("part_lo", box[0])
            self.register_buffer("part_hi", box[1])
        self.part_bounded = box is not None
        if self.part_bounded:
            self.part_volume_fraction = float(torch.prod((box[1] - box[0]) / 2.0))

    def angle(self, t: torch.Tensor) -> torch.Tensor:
        """The joint angle (radians) at normalised times ``t`` (any shape), linear between samples."""
        return lerp_table(self.angles, t.reshape(-1)).reshape(t.shape)

    def part_frame(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Box-normalised world points -> the moving part's frame (rotated by -angle(t) about
        the joint, in metres), box-normalised again (with a ``part_box``: normalised to it)."""
        w = (x - self.pivot) * self.half_extent
        theta = -self.angle(t.reshape(-1))
        c, s = torch.cos(theta).unsqueeze(1), torch.sin(theta).unsqueeze(1)
        k = self.axis.expand_as(w)
        # Rodrigues: w cos + (k x w) sin + k (k . w)(1 - cos)
        rotated = w * c + torch.cross(k, w, dim=1) * s + k * (w @ self.axis).unsqueeze(1) * (1.0 - c)
        p = rotated / self.half_extent + self.pivot
        if self.part_bounded:
            p = (p - self.part_lo) / (self.part_hi - self.part_lo) * 2.0 - 1.0
        return p

    def part_inputs(self, t: torch.Tensor) -> torch.Tensor | None:
        if not self.shading:
            return None
        theta = self.angle(t)
        return torch.stack([torch.cos(theta), torch.sin(theta)], dim=1)
