"""Voxels: indices, one point per voxel, centroids, dense counts."""

from __future__ import annotations

import numpy as np
import pytest

from app.geometry.voxels import voxel_counts, voxel_downsample, voxel_indices, voxel_means


def test_voxel_indices_floor_with_origin() -> None:
    xyz = np.array([[0.05, 0.15, -0.05], [1.0, 1.0, 1.0]])
    np.testing.assert_array_equal(voxel_indices(xyz, 0.1), [[0, 1, -1], [10, 10, 10]])
    np.testing.assert_array_equal(
        voxel_indices(xyz, 0.5, origin=np.array([-1.0, 0.0, 0.0])), [[2, 0, -1], [4, 2, 2]]
    )
    assert voxel_indices(xyz, 0.1).dtype == np.int64


def test_voxel_downsample_keeps_first_point_of_each_voxel() -> None:
    xyz = np.array(
        [
            [0.05, 0.05, 0.05],  # voxel A, first
            [0.5, 0.5, 0.5],  # voxel B, first
            [0.06, 0.02, 0.09],  # voxel A again
            [-0.05, 0.05, 0.05],  # voxel C (negative)
            [0.51, 0.55, 0.58],  # voxel B again
        ]
    )
    np.testing.assert_array_equal(voxel_downsample(xyz, 0.1), [0, 1, 3])


def test_voxel_downsample_one_point_per_occupied_voxel() -> None:
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-5, 5, (20_000, 3)) + np.array([456_000.0, 5_400_000.0, 100.0])
    keep = voxel_downsample(xyz, 0.5)
    assert np.all(np.diff(keep) > 0)
    ijk = voxel_indices(xyz, 0.5)
    occupied = np.unique(ijk, axis=0)
    kept = ijk[keep]
    assert len(np.unique(kept, axis=0)) == len(kept) == len(occupied)
    # Every kept index is the first occurrence of its voxel.
    _, first = np.unique(ijk, axis=0, return_index=True)
    np.testing.assert_array_equal(keep, np.sort(first))


def test_voxel_means_are_centroids() -> None:
    xyz = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 1.5, 1.5], [-0.5, 0.2, 0.2]])
    means = voxel_means(xyz, 1.0)
    expected = {(0.2, 0.2, 0.2), (1.5, 1.5, 1.5), (-0.5, 0.2, 0.2)}
    assert {tuple(np.round(m, 9)) for m in means} == expected


def test_voxel_counts_dense_and_drops_outside() -> None:
    ijk = np.array([[0, 0, 0], [0, 0, 0], [1, 1, 29], [1, 1, 30], [-1, 0, 0], [0, 2, 0]])
    grid = voxel_counts(ijk, (2, 2, 30))
    assert grid.shape == (2, 2, 30) and grid.dtype == np.int32
    assert grid[0, 0, 0] == 2 and grid[1, 1, 29] == 1
    assert grid.sum() == 3


def test_voxel_counts_empty_and_bad_shape() -> None:
    assert voxel_counts(np.zeros((0, 3), dtype=np.int64), (2, 2, 3)).sum() == 0
    with pytest.raises(ValueError, match="ijk"):
        voxel_counts(np.zeros((4, 2), dtype=np.int64), (2, 2, 3))
