"""An occupancy grid over the scene box for empty-space skipping.

``occupied[ix, iy, iz]`` (bool, axis order x, y, z) marks cells that may hold density.
It is built either from the field (``update``: the max over a few times of the density
at the cell centres, thresholded, optionally dilated by whole cells to cover what lies
between centres) or from an *event footprint* (``from_footprint``: a boolean voxel grid,
e.g. voxels seen by event pixels; resampled by nearest neighbour to the grid).

``enabled = False`` switches skipping off (``query`` then returns all True), so a run
can measure the saving.  Coordinates given to ``query`` are box-normalised [-1, 1].
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F


def grid_lookup(grid: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Value of the cell (nearest, clamped) of a (Rx, Ry, Rz) grid spanning [-1, 1]^3 at
    each of the (N, 3) normalised points."""
    res = torch.tensor(grid.shape, device=x.device)
    i = ((x + 1.0) * 0.5 * res).long()
    # one clamp against both bounds, then one gather by flat index (3x faster than a clamp, a
    # minimum and three index tensors at a million points; the same cells)
    i = torch.clamp(i, min=torch.zeros_like(res), max=res - 1)
    g = grid.to(x.device)
    flat = (i[:, 0] * grid.shape[1] + i[:, 1]) * grid.shape[2] + i[:, 2]
    return g.reshape(-1)[flat]


def cells_box(grid: torch.Tensor, box) -> np.ndarray | None:
    """(2, 3) world box around the True cells of a boolean (Rx, Ry, Rz) grid spanning ``box``,
    padded by a thousandth of the box so that float rounding never puts a point of such a
    cell outside it; None when no cell is True."""
    idx = torch.nonzero(grid)
    if not idx.numel():
        return None
    lo, hi = np.asarray(box, np.float64).reshape(2, 3)
    res = np.asarray(grid.shape, np.float64)
    first, last = idx.amin(0).cpu().numpy(), idx.amax(0).cpu().numpy() + 1
    pad = 1e-3 * (hi - lo)
    return np.stack([lo + (hi - lo) * first / res - pad, lo + (hi - lo) * last / res + pad])


class OccupancyGrid:
    def __init__(self, resolution: int | Sequence[int] = 32, enabled: bool = True):
        r = (int(resolution),) * 3 if isinstance(resolution, int) else tuple(
            int(v) for v in resolution)
        if len(r) != 3 or min(r) < 1:
            raise ValueError(f"occupancy resolution must be 1 or 3 positive ints, got {resolution}")
        self.resolution = r
        self.enabled = bool(enabled)
        self.occupied = torch.ones(r, dtype=torch.bool)
        self.density_max = torch.full(r, float("inf"))

    def to(self, device) -> "OccupancyGrid":
        """The grids moved to ``device`` (where the points it is queried with live)."""
        self.occupied = self.occupied.to(device)
        self.density_max = self.density_max.to(device)
        return self

    def cell_centres(self, device=None) -> torch.Tensor:
        """(Rx*Ry*Rz, 3) normalised cell centres, C order (x slowest)."""
        axes = [(torch.arange(n, dtype=torch.float32, device=device) + 0.5) / n * 2.0 - 1.0
                for n in self.resolution]
        g = torch.meshgrid(*axes, indexing="ij")
        return torch.stack(g, dim=-1).reshape(-1, 3)

    @torch.no_grad()
    def update(self, field, times: Sequence[float] = (0.0, 0.5, 1.0),
               threshold: float = 0.01, dilate: int = 1, chunk: int = 65536):
        """occupied = dilate(max_t density(cell centre, t) > threshold), on the field's device."""
        from ..device import module_device

        dev = module_device(field)
        x = self.cell_centres(dev)
        dmax = torch.zeros(x.shape[0], device=dev)
        for s in range(0, x.shape[0], chunk):
            xs = x[s:s + chunk]
            cols = [torch.full((xs.shape[0], 1), float(t), device=dev) for t in times]
            for dens, _ in field.evaluate_times(xs, cols):
                dmax[s:s + chunk] = torch.maximum(dmax[s:s + chunk], dens.float())
        self.density_max = dmax.reshape(self.resolution)
        self.occupied = self._dilate(self.density_max > threshold, dilate)
        return self

    @classmethod
    def from_footprint(cls, footprint, resolution=None, dilate: int = 0,
                       enabled: bool = True) -> "OccupancyGrid":
        """Grid from a boolean voxel footprint (axis order x, y, z) spanning the box."""
        fp = torch.as_tensor(footprint).bool()
        if fp.dim() != 3:
            raise ValueError(f"footprint must be a 3D boolean grid, got shape {tuple(fp.shape)}")
        grid = cls(tuple(fp.shape) if resolution is None else resolution, enabled)
        occ = fp
        if tuple(fp.shape) != grid.resolution:
            occ = F.interpolate(fp[None, None].float(), size=grid.resolution,
                                mode="nearest")[0, 0] > 0.5
        grid.occupied = cls._dilate(occ, dilate)
        grid.density_max = torch.where(grid.occupied, float("inf"), 0.0)
        return grid

    @staticmethod
    def _dilate(occ: torch.Tensor, cells: int) -> torch.Tensor:
        if cells <= 0:
            return occ.clone()
        k = 2 * int(cells) + 1
        return F.max_pool3d(occ[None, None].float(), k, stride=1, padding=int(cells))[0, 0] > 0.5

    def query(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) normalised points -> (N,) bool, True where the cell may be occupied."""
        if not self.enabled:
            return torch.ones(x.shape[0], dtype=torch.bool, device=x.device)
        return grid_lookup(self.occupied, x)

    @property
    def fraction_occupied(self) -> float:
        return float(self.occupied.float().mean())
