"""A learned background: grey as a function of the ray's world direction.

Rays that leave the scene box unoccluded see what lies beyond it.  A simulated scene's
backdrop (``sim.render``: ``intensity * texture(direction)``), like a real room far from
the rig, is an environment at infinity: its grey depends on the ray's direction only, the
same for every view.  A constant background grey cannot show it, and a view-independent
field cannot paint it inside the box either (what is behind the box for one view lies in
front of it for the opposite view), yet every event where a moving object uncovers the
backdrop measures log(backdrop) - log(object).  ``BackgroundMap`` learns it as an
equirectangular grid of logits over azimuth (about the world z axis) and elevation,
bilinear, wrapping in azimuth, grey = sigmoid(logit) in (0, 1).

Its signal is sparse (only the directions seen behind moving things carry events), so the
grid is the sum of a coarse and a fine level: the coarse level spreads what a few events
say over its neighbourhood, the fine one adds the detail.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

#: Azimuth cells of the coarse level as a fraction of the fine level's.
COARSE_FRACTION = 8


class BackgroundMap(nn.Module):
    def __init__(self, cells: int, grey: float):
        """``cells``: azimuth cells of the fine level (elevation: half as many);
        ``grey``: the initial grey everywhere, in (0, 1)."""
        super().__init__()
        cells = int(cells)
        if cells < 8:
            raise ValueError(f"background map needs at least 8 azimuth cells, got {cells}")
        if not 0.0 < float(grey) < 1.0:
            raise ValueError(f"background map's initial grey must be in (0, 1), got {grey}")
        self.cells = cells
        logit = math.log(grey / (1.0 - grey))
        coarse = max(4, cells // COARSE_FRACTION)
        self.coarse = nn.Parameter(torch.full((1, 1, coarse // 2 + 1, coarse), logit))
        self.fine = nn.Parameter(torch.zeros(1, 1, cells // 2 + 1, cells))

    @staticmethod
    def _lookup(grid: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        # the first column again after the last, so azimuth +pi meets -pi (wrap)
        wrapped = torch.cat([grid, grid[..., :1]], dim=3)
        out = F.grid_sample(wrapped, coords.view(1, -1, 1, 2), mode="bilinear",
                            padding_mode="border", align_corners=True)
        return out.view(-1)

    def forward(self, dirs: torch.Tensor) -> torch.Tensor:
        """(N, 3) world directions (any length) -> (N,) grey in (0, 1)."""
        d = dirs.to(torch.float32)
        horizontal = torch.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)
        azimuth = torch.atan2(d[:, 1], d[:, 0]) / math.pi                 # [-1, 1]
        elevation = torch.atan2(d[:, 2], horizontal) / (0.5 * math.pi)   # [-1, 1]
        # grid x = azimuth (columns), grid y = elevation (rows)
        coords = torch.stack([azimuth, elevation], dim=1)
        return torch.sigmoid(self._lookup(self.coarse, coords) + self._lookup(self.fine, coords))
