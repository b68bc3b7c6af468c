"""The two density-based reference methods of the phantom paper's Table II (Sec. IV-C).

Both work on the accumulated map, `xyz` (N, 3) float64 world coordinates, and return (N,) bool
flags, True = "phantom". Defaults are the paper's numbers (r = 0.2 m, t = 100, k = 100).

- *Num of neighbors* (`num_neighbors`): radius outlier removal; a point is phantom when it has
  fewer than t neighbours within r.
- *Avg distances* (`avg_distances`): PCL's StatisticalOutlierRemoval; a point is phantom when its
  mean distance to its k nearest neighbours exceeds mean + std_ratio * std of those means.

Neighbour search is one scipy cKDTree over the whole map, queried in chunks of points
(`chunk_size`) with `workers=-1`, so memory stays bounded for maps of tens of millions of points;
results do not depend on the chunk size. Coordinates are re-centred on their mean first
(distances are unchanged, fewer bits are lost on large world coordinates).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

PointsDone = Callable[[int, int], None]  # (points done, points in all)

NUM_NEIGHBORS_CHUNK = 1_000_000  # counts only: 8 bytes per point of the chunk
AVG_DISTANCES_CHUNK = 100_000  # (k + 1) distances and indices per point: ~160 MB at k = 100


def _checked(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be an (N, 3) array, got shape {xyz.shape}")
    if not np.isfinite(xyz).all():
        raise ValueError("xyz holds NaN or infinite coordinates")
    if len(xyz) == 0:
        return xyz
    return xyz - xyz.mean(axis=0)


def _tree(xyz: np.ndarray) -> cKDTree:
    # balanced_tree / compact_nodes off: much faster to build on large maps, same answers
    return cKDTree(xyz, balanced_tree=False, compact_nodes=False)


def _chunks(n: int, chunk_size: int) -> range:
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be at least 1, got {chunk_size}")
    return range(0, n, chunk_size)


def neighbor_counts(
    xyz: np.ndarray,
    radius: float = 0.2,  # r
    chunk_size: int = NUM_NEIGHBORS_CHUNK,
    progress: PointsDone | None = None,
) -> np.ndarray:
    """(N,) int64: number of *other* points within `radius` (distance <= r) of each point.

    The point itself is not counted; duplicates of it (other points at distance 0) are.
    """
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    xyz = _checked(xyz)
    n = len(xyz)
    counts = np.zeros(n, dtype=np.int64)
    if n == 0:
        return counts
    tree = _tree(xyz)
    for start in _chunks(n, chunk_size):
        stop = min(n, start + chunk_size)
        found = tree.query_ball_point(xyz[start:stop], r=radius, return_length=True, workers=-1)
        counts[start:stop] = np.asarray(found, dtype=np.int64) - 1  # minus the point itself
        if progress is not None:
            progress(stop, n)
    return counts


def num_neighbors(
    xyz: np.ndarray,
    radius: float = 0.2,  # r, metres
    threshold: int = 100,  # t
    chunk_size: int = NUM_NEIGHBORS_CHUNK,
    progress: PointsDone | None = None,
) -> np.ndarray:
    """(N,) bool: phantom where a point has fewer than t other points within r.

    "Num of neighbors" of Table II: neighbours are counted excluding the point itself (PCL's
    RadiusOutlierRemoval convention); a point with exactly t neighbours is kept.
    """
    return neighbor_counts(xyz, radius, chunk_size, progress) < threshold


def mean_neighbor_distances(
    xyz: np.ndarray,
    k: int = 100,  # k
    chunk_size: int = AVG_DISTANCES_CHUNK,
    progress: PointsDone | None = None,
) -> np.ndarray:
    """(N,) float64: mean distance of each point to its k nearest *other* points.

    The query asks for k + 1 neighbours and drops the nearest one (the point itself, or a
    duplicate of it at the same distance 0). With N <= k every point averages its N - 1 others;
    a lone point gets 0.
    """
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    xyz = _checked(xyz)
    n = len(xyz)
    means = np.zeros(n, dtype=np.float64)
    k_eff = min(int(k), n - 1)
    if k_eff < 1:
        return means
    tree = _tree(xyz)
    for start in _chunks(n, chunk_size):
        stop = min(n, start + chunk_size)
        distances, _ = tree.query(xyz[start:stop], k=k_eff + 1, workers=-1)
        means[start:stop] = distances[:, 1:].mean(axis=1)
        if progress is not None:
            progress(stop, n)
    return means


def avg_distances(
    xyz: np.ndarray,
    k: int = 100,  # k
    std_ratio: float = 1.0,  # PCL's stddev multiplier
    chunk_size: int = AVG_DISTANCES_CHUNK,
    progress: PointsDone | None = None,
) -> np.ndarray:
    """(N,) bool: phantom where the mean k-NN distance is above mean + std_ratio * std.

    "Avg distances" of Table II, PCL's StatisticalOutlierRemoval: first pass, each point's mean
    distance to its k nearest neighbours (itself excluded); second pass, threshold = mean +
    std_ratio * std of those means over the whole map (std with N - 1 in the denominator, as PCL
    computes it); points strictly above the threshold are outliers, i.e. phantom.
    """
    means = mean_neighbor_distances(xyz, k, chunk_size, progress)
    if len(means) < 2:
        return np.zeros(len(means), dtype=bool)
    threshold = means.mean() + std_ratio * means.std(ddof=1)
    return means > threshold
