"""Voxel indexing, downsampling and dense counting (phantom pipeline: 2x2x30 voxels per pillar).

Voxel keys are packed into one int64 per point so grouping is a 1-D sort, not np.unique(axis=0).
"""

from __future__ import annotations

import numpy as np

from app.geometry._arrays import as_points


def voxel_indices(
    xyz: np.ndarray, voxel_size: float, origin: np.ndarray | None = None
) -> np.ndarray:
    """(N, 3) int64 index of the voxel holding each point: floor((xyz - origin) / voxel_size)."""
    xyz = as_points(xyz)
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    if origin is None:
        return np.floor(xyz / voxel_size).astype(np.int64)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    return np.floor((xyz - origin) / voxel_size).astype(np.int64)


def voxel_keys(ijk: np.ndarray) -> np.ndarray:
    """(N,) int64 key per voxel index row, equal exactly when the rows are equal (within a call)."""
    ijk = np.asarray(ijk, dtype=np.int64)
    if len(ijk) == 0:
        return np.zeros(0, dtype=np.int64)
    low = ijk.min(axis=0)
    dims = ijk.max(axis=0) - low + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:
        return np.ravel_multi_index(tuple((ijk - low).T), tuple(int(d) for d in dims))
    # Extent too large to pack: fall back to a row-wise unique (slower, but exact).
    return np.unique(ijk, axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)


def voxel_downsample(
    xyz: np.ndarray, voxel_size: float, origin: np.ndarray | None = None
) -> np.ndarray:
    """Indices (ascending) of one point per occupied voxel: the first one in input order."""
    keys = voxel_keys(voxel_indices(xyz, voxel_size, origin))
    # np.unique sorts stably when asked for indices, so each index is the first occurrence.
    _, first = np.unique(keys, return_index=True)
    return np.sort(first)


def voxel_means(xyz: np.ndarray, voxel_size: float, origin: np.ndarray | None = None) -> np.ndarray:
    """(M, 3) centroid of the points of each occupied voxel (voxels in key order)."""
    xyz = as_points(xyz)
    keys = voxel_keys(voxel_indices(xyz, voxel_size, origin))
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.stack(
        [np.bincount(inverse, weights=xyz[:, k], minlength=len(counts)) for k in range(3)], axis=1
    )
    return sums / counts[:, None]


def voxel_counts(ijk: np.ndarray, shape: tuple[int, int, int] | np.ndarray) -> np.ndarray:
    """Dense int32 grid of `shape` counting points per voxel; indices outside it are dropped."""
    ijk = np.asarray(ijk, dtype=np.int64)
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise ValueError(f"ijk must have shape (N, 3), got {ijk.shape}")
    dims = tuple(int(d) for d in np.asarray(shape).reshape(3))
    inside = np.all((ijk >= 0) & (ijk < np.array(dims)), axis=1)
    flat = np.ravel_multi_index(tuple(ijk[inside].T), dims)
    counts = np.bincount(flat, minlength=int(np.prod(dims)))
    return counts.astype(np.int32).reshape(dims)
