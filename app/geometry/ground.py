"""Local ground height: phantom pillars reach 3 m above it, clutter clusters start above it.

Per `ground_cell` x `ground_cell` cell the 5th percentile of z; a grey opening (minimum then
maximum filter over `ground_opening` cells) removes anything narrower than that which covers whole
cells (car roofs, kiosks); empty cells take the nearest estimate. Heights are read back per point
by bilinear interpolation, so slopes do not step at cell borders.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass
class GroundModel:
    origin: np.ndarray  # (2,) xy of cell (0, 0)'s centre
    cell: float
    heights: np.ndarray  # (NX, NY) float64

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height under each xy (bilinear between cell centres, clamped at the border)."""
        f = (np.asarray(xy)[:, :2] - self.origin) / self.cell
        nx, ny = self.heights.shape
        fx = np.clip(f[:, 0], 0, nx - 1)
        fy = np.clip(f[:, 1], 0, ny - 1)
        x0 = np.minimum(np.floor(fx).astype(np.int64), max(nx - 2, 0))
        y0 = np.minimum(np.floor(fy).astype(np.int64), max(ny - 2, 0))
        x1, y1 = np.minimum(x0 + 1, nx - 1), np.minimum(y0 + 1, ny - 1)
        tx, ty = fx - x0, fy - y0
        h = self.heights
        return (
            h[x0, y0] * (1 - tx) * (1 - ty)
            + h[x1, y0] * tx * (1 - ty)
            + h[x0, y1] * (1 - tx) * ty
            + h[x1, y1] * tx * ty
        )


def estimate_ground(
    xyz: np.ndarray, cell: float = 1.0, opening: int = 5, margin: int = 0
) -> GroundModel:
    """The ground under `xyz`. With `margin` >= `opening` the grid reaches that many empty cells
    beyond the points on every side, so its edge never meets the opening of a cell with points:
    the ground at a point then does not depend on how far the map reaches elsewhere (a tile's
    window of a map gets the ground the whole map gets there). Without, the grid ends at the
    points' bounding box, where the opening repeats the edge cells."""
    lo = np.floor(xyz[:, :2].min(axis=0) / cell) * cell - margin * cell
    ij = np.floor((xyz[:, :2] - lo) / cell).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 1 + margin)
    flat = np.ravel_multi_index((ij[:, 0], ij[:, 1]), shape)
    # 5th percentile per cell: sort by (cell, z) once, pick the rank inside each cell
    order = np.lexsort((xyz[:, 2], flat))
    cells, start, count = np.unique(flat[order], return_index=True, return_counts=True)
    pick = start + np.floor(0.05 * (count - 1)).astype(np.int64)
    grid = np.full(shape, np.nan)
    grid.ravel()[cells] = xyz[order[pick], 2]
    empty = np.isnan(grid)
    if empty.any():  # nearest filled cell
        _, (ix, iy) = ndimage.distance_transform_edt(empty, return_indices=True)
        grid = grid[ix, iy]
    grid = ndimage.grey_opening(grid, size=(opening, opening), mode="nearest")
    return GroundModel(origin=lo + cell / 2, cell=cell, heights=grid)
