"""2D pillar grid on the horizontal plane (phantom pipeline: 0.2 m x 0.2 m pillars).

Cell ids are packed from the integer cell indices, not numbered by occurrence, so the same place
gets the same id whichever points were loaded: labels stored per pillar survive re-runs and
overlapping tiles as long as the origin and cell size are the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_OFFSET = np.int64(2**31)
_LOW = np.uint64(0xFFFFFFFF)
_MIN_INDEX = -(2**31)
_MAX_INDEX = 2**31 - 1


@dataclass(frozen=True)
class PillarGrid:
    """Cell (ix, iy) covers [origin + i * cell_size, origin + (i + 1) * cell_size) on each axis."""

    origin_x: float
    origin_y: float
    cell_size: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.cell_size) and self.cell_size > 0):
            raise ValueError(f"cell_size must be a positive number, got {self.cell_size}")

    @classmethod
    def aligned(cls, xy: np.ndarray, cell_size: float) -> PillarGrid:
        """Grid whose origin is a multiple of cell_size, so overlapping runs share cell borders."""
        xy = _xy(xy)
        if len(xy) == 0 or not cell_size > 0:
            return cls(0.0, 0.0, float(cell_size))  # validates cell_size
        origin = np.floor(xy.min(axis=0) / cell_size) * cell_size
        return cls(float(origin[0]), float(origin[1]), float(cell_size))

    @property
    def origin(self) -> np.ndarray:
        """(2,) float64 origin."""
        return np.array([self.origin_x, self.origin_y])

    def addressable(self) -> tuple[np.ndarray, np.ndarray]:
        """(2,) lowest and highest world x, y whose cell index fits the 32 bits `cell_id` packs
        per axis: a coordinate outside this range has no cell id."""
        return self.origin + _MIN_INDEX * self.cell_size, self.origin + _MAX_INDEX * self.cell_size

    def cell_index(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) int64 cell indices (floor); extra columns (z) are ignored."""
        xy = _xy(xy)
        return np.floor((xy - self.origin) / self.cell_size).astype(np.int64)

    def cell_id(self, ix: np.ndarray | int, iy: np.ndarray | int) -> np.ndarray:
        """Stable int64 id ((ix + 2**31) << 32) | (iy + 2**31), wrapped from uint64 bits."""
        ix = np.asarray(ix, dtype=np.int64)
        iy = np.asarray(iy, dtype=np.int64)
        if ix.size and (ix.min() < _MIN_INDEX or ix.max() > _MAX_INDEX):
            raise ValueError("cell index ix is beyond 32 bits; choose an origin nearer the data")
        if iy.size and (iy.min() < _MIN_INDEX or iy.max() > _MAX_INDEX):
            raise ValueError("cell index iy is beyond 32 bits; choose an origin nearer the data")
        hi = (ix + _OFFSET).astype(np.uint64) << np.uint64(32)
        lo = (iy + _OFFSET).astype(np.uint64)
        packed = (hi | lo).view(np.int64)
        return packed if packed.ndim else packed[()]

    def decode(self, ids: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """(ix, iy) int64 back from packed ids."""
        bits = np.asarray(ids, dtype=np.int64).view(np.uint64)
        ix = (bits >> np.uint64(32)).astype(np.int64) - _OFFSET
        iy = (bits & _LOW).astype(np.int64) - _OFFSET
        return ix, iy

    def cell_center(self, ix: np.ndarray | int, iy: np.ndarray | int) -> np.ndarray:
        """(N, 2) float64 centre of each cell."""
        ix = np.atleast_1d(np.asarray(ix, dtype=np.float64))
        iy = np.atleast_1d(np.asarray(iy, dtype=np.float64))
        return np.stack(
            [
                self.origin_x + (ix + 0.5) * self.cell_size,
                self.origin_y + (iy + 0.5) * self.cell_size,
            ],
            axis=1,
        )

    def point_cell_ids(self, xy: np.ndarray) -> np.ndarray:
        """(N,) int64 stable id of the cell each point falls in."""
        idx = self.cell_index(xy)
        return self.cell_id(idx[:, 0], idx[:, 1])

    def group(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(unique_ids, inverse, counts): occupied cells, each point's cell row, points per cell."""
        ids = self.point_cell_ids(xy)
        unique_ids, inverse, counts = np.unique(ids, return_inverse=True, return_counts=True)
        return unique_ids, inverse.reshape(-1), counts


def _xy(values: np.ndarray) -> np.ndarray:
    """Horizontal coordinates of (N, 2) or (N, 3+) points as float64 (N, 2)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] < 2:
        raise ValueError(f"xy must have shape (N, 2) or (N, 3), got {arr.shape}")
    return arr[:, :2]
