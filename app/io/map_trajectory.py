"""Where the scanner went, for a map file that does not say: from its points, in one pass.

Tiles follow the trajectory (`geometry.tiles`). A LAS map written by another tool carries no
trajectory, but its points do: with GPS times, the points measured in the same second lie around
where the vehicle was then, so the centroids of one-second bins in time order trace the drive
(through stops and turns, and a street driven twice). Without times (or with all times equal,
as writers that do not record them leave them), the map's principal axis stands in: centroids of
10 m bins along it. Either way the path only decides which tile owns a point; the halo around
each tile is spatial, so a rough path costs nothing but uneven tiles.
"""

from __future__ import annotations

import numpy as np

from app.io.survey import Survey

BIN_SECONDS = 1.0  # points of one second share a trajectory position
AXIS_STEP = 10.0  # metres between positions along the principal axis
GRID_CELL = 10.0  # metres: the point sums the axis fallback keeps
MIN_STEP = 1.0  # metres: closer consecutive positions (a stop) are merged


def map_trajectory(survey: Survey) -> tuple[np.ndarray, float | None]:
    """(M, 3) positions in driving order, and the first point time (None when the map has no
    usable times)."""
    time_parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    grid_parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    t_low, t_high, timed = np.inf, -np.inf, True
    for frame in survey.frames:
        for _, cloud in frame.world_chunks():
            xyz = cloud.xyz
            if not len(xyz):
                continue
            grid_parts.append(_sums(np.floor(xyz[:, :2] / GRID_CELL).astype(np.int64), xyz))
            t = cloud.time
            if t is None or not np.all(np.isfinite(t)):
                timed = False
            if timed:
                t_low, t_high = min(t_low, float(t.min())), max(t_high, float(t.max()))
                time_parts.append(_sums(np.floor(t / BIN_SECONDS).astype(np.int64)[:, None], xyz))
    if not grid_parts:
        raise ValueError(f"{survey.source}: no points to find a trajectory in")
    if timed and t_high > t_low:
        _, sums, counts = _reduce(time_parts)  # keys ascending: time order
        return _thinned(sums / counts[:, None]), t_low
    return _thinned(_along_axis(*_reduce(grid_parts))), None


def _sums(keys: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unique key rows, sum of xyz per key, count per key)."""
    unique, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.stack([np.bincount(inverse, xyz[:, k], len(unique)) for k in range(3)], axis=1)
    return unique, sums, counts


def _reduce(parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    keys = np.concatenate([p[0] for p in parts])
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(unique), 3))
    np.add.at(sums, inverse, np.concatenate([p[1] for p in parts]))
    counts = np.bincount(inverse, np.concatenate([p[2] for p in parts]), len(unique))
    return unique, sums, counts


def _along_axis(_: np.ndarray, sums: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Centroids of AXIS_STEP bins along the principal axis of the grid cells' centroids."""
    centres = sums / counts[:, None]
    weights = counts / counts.sum()
    mean = weights @ centres[:, :2]
    offset = centres[:, :2] - mean
    covariance = (offset * weights[:, None]).T @ offset
    axis = np.linalg.eigh(covariance)[1][:, -1]
    along = offset @ axis
    bins = np.floor(along / AXIS_STEP).astype(np.int64)
    _, inverse = np.unique(bins, return_inverse=True)
    inverse = inverse.reshape(-1)
    total = np.zeros((inverse.max() + 1, 3))
    np.add.at(total, inverse, sums)
    return total / np.bincount(inverse, counts)[:, None]


def _thinned(positions: np.ndarray) -> np.ndarray:
    """Consecutive positions closer than MIN_STEP merged into the first (a stop)."""
    kept = [0]
    for k in range(1, len(positions)):  # one per trajectory position, not per point
        if np.linalg.norm(positions[k, :2] - positions[kept[-1], :2]) >= MIN_STEP:
            kept.append(k)
    return positions[kept]
