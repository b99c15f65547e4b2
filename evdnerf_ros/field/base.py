"""The field interface shared by every backbone.

A field maps a point ``x`` and a normalised time ``t`` to a volume density and a grey
(linear) intensity:

    forward(x, t) -> (density, grey)

- ``x``: (N, 3) float32, scene-box-normalised coordinates in [-1, 1] (see
  ``render.normalize_points``); points outside are clamped by the renderer.
- ``t``: (N, 1) float32 in [0, 1].  It is computed by the caller from int64 nanosecond
  differences (DESIGN.md), never from float seconds.
- ``density``: (N,) float32 >= 0, per metre of world distance along the ray.
- ``grey``: (N,) float32 in (0, 1), linear intensity (no view dependence).

Static-view sample reuse: a training view's camera does not move, so the samples along
a ray are the same at t_{k-1} and t_k.  Every field therefore offers

    feats = field.space_features(x)      # the time-independent part, computed once
    density, grey = field.decode(feats, t)

with ``decode(space_features(x), t)`` *bit-identical* to ``forward(x, t)``.  The generic
fallback (this base class) has ``space_features`` return ``x`` itself and ``decode`` call
``forward``, i.e. it evaluates the full field twice; backbones with a factorised
representation (``planes``) override both so that only the time-dependent lookups are
repeated.  ``evaluate_times(x, times)`` is the convenience wrapper.

Static points: ``decode_static(space_features(x))`` is the field with no time dependence
(planes: the time factors taken as 1; dnerf: no deformation).  ``evaluate_times(x, times,
dynamic)`` uses it, evaluated once for all times, where the boolean ``dynamic`` is False
(points outside ``DynamicRegion``).
"""

from __future__ import annotations

import abc
from typing import Any, Sequence

import torch
from torch import nn


class DynamicField(nn.Module, abc.ABC):
    """Base class: subclasses implement ``forward`` (and optionally the reuse pair)."""

    #: True where ``space_features``/``decode`` actually save work.
    reuses_space_features: bool = False

    # ``background_map``: a learned ``BackgroundMap`` (grey per ray direction) that
    # ``make_field`` may attach as a submodule (saved with the field's weights); absent, the
    # renderer's constant background is used (``render.background_grey``).  Not a class
    # attribute: that would shadow the submodule nn.Module keeps in ``_modules``.

    @abc.abstractmethod
    def forward(self, x: torch.Tensor, t: torch.Tensor):
        """(N, 3) normalised x, (N, 1) t -> (density (N,), grey (N,))."""

    def param_groups(self) -> list[tuple[list, float]]:
        """[(parameters, learning-rate scale)]: every parameter at the trainer's rate (a field
        with parameters of another scale, ``rigid``'s poses, splits them)."""
        return [(list(self.parameters()), 1.0)]

    def space_features(self, x: torch.Tensor) -> Any:
        """Time-independent features of ``x`` (generic fallback: ``x`` itself)."""
        return x

    def decode(self, features: Any, t: torch.Tensor):
        """(density, grey) at time ``t`` from ``space_features(x)``."""
        return self.forward(features, t)

    @abc.abstractmethod
    def decode_static(self, features: Any):
        """(density, grey) of the static field (no time dependence) from ``space_features(x)``."""

    def evaluate_times(self, x: torch.Tensor, times: Sequence[torch.Tensor],
                       dynamic: torch.Tensor | None = None):
        """[(density, grey) for each t in ``times``], sharing the space features.

        ``dynamic``: optional (N,) bool; False points take the static field, evaluated once.
        """
        if dynamic is None:
            feats = self.space_features(x)
            return [self.decode(feats, t) for t in times]
        d_idx = torch.nonzero(dynamic, as_tuple=False).squeeze(1)
        s_idx = torch.nonzero(~dynamic, as_tuple=False).squeeze(1)
        n = x.shape[0]
        empty = torch.zeros(n, dtype=torch.float32, device=x.device)
        static = self.decode_static(self.space_features(x[s_idx])) if s_idx.numel() else None
        feats = self.space_features(x[d_idx]) if d_idx.numel() else None
        out = []
        for t in times:
            density, grey = empty, empty
            if static is not None:
                density = density.index_put((s_idx,), static[0])
                grey = grey.index_put((s_idx,), static[1])
            if feats is not None:
                dd, gd = self.decode(feats, t[d_idx] if t.shape[0] == n else t)
                density = density.index_put((d_idx,), dd)
                grey = grey.index_put((d_idx,), gd)
            out.append((density, grey))
        return out


def normalized_time(t_ns, t_start_ns: int, t_end_ns: int) -> torch.Tensor:
    """int64 nanoseconds -> float32 normalised time in [0, 1] (clamped).

    The difference ``t_ns - t_start_ns`` is taken in int64 and only then divided (in
    float64), so absolute timestamps around 1e4 s keep their nanoseconds (DESIGN.md).
    """
    import numpy as np

    t = np.asarray(t_ns, dtype=np.int64)
    t0, t1 = np.int64(t_start_ns), np.int64(t_end_ns)
    if t1 <= t0:
        raise ValueError(f"time range must have end > start, got {t_start_ns}..{t_end_ns}")
    u = (t - t0).astype(np.float64) / float(t1 - t0)
    return torch.as_tensor(np.clip(u, 0.0, 1.0), dtype=torch.float32)


def as_time_column(t, n: int, device=None) -> torch.Tensor:
    """A float, (N,), (N, 1) or (1,) time -> (n, 1) float32 tensor."""
    t = torch.as_tensor(t, dtype=torch.float32, device=device)
    if t.dim() == 0:
        return t.reshape(1, 1).expand(n, 1)
    t = t.reshape(-1, 1)
    if t.shape[0] == 1:
        return t.expand(n, 1)
    if t.shape[0] != n:
        raise ValueError(f"time has {t.shape[0]} entries for {n} points")
    return t
