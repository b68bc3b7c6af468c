"""Table II reference methods: Num of neighbors (radius count) and Avg distances (SOR)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from app.pipelines.phantom.evaluation.baselines import (
    avg_distances,
    mean_neighbor_distances,
    neighbor_counts,
    num_neighbors,
)


def _plane(step: float = 0.02, size: float = 2.0, seed: int = 0) -> np.ndarray:
    """Dense horizontal plane, a jittered grid: ~314 points within 0.2 m of an interior point."""
    g = np.arange(0.0, size, step)
    x, y = np.meshgrid(g, g, indexing="ij")
    rng = np.random.default_rng(seed)
    xy = np.column_stack([x.ravel(), y.ravel()]) + rng.uniform(-0.002, 0.002, (x.size, 2))
    return np.column_stack([xy, np.zeros(len(xy))])


def test_num_neighbors_flags_sparse_smear_not_plane_interior() -> None:
    plane = _plane()
    # a sparse line 1 m above the plane, 0.1 m apart: at most 4 neighbours within 0.2 m
    smear = np.column_stack([np.linspace(0.2, 1.8, 17), np.full(17, 1.0), np.full(17, 1.0)])
    xyz = np.vstack([plane, smear]) + np.array([4.5e5, 5.4e6, 100.0])  # UTM-sized coordinates
    flags = num_neighbors(xyz)  # r = 0.2, t = 100
    assert flags.dtype == bool and flags.shape == (len(xyz),)
    assert flags[len(plane) :].all()
    interior = (plane[:, :2].min(axis=1) > 0.25) & (plane[:, :2].max(axis=1) < 2.0 - 0.25)
    assert interior.sum() > 5_000
    assert not flags[: len(plane)][interior].any()


def test_neighbor_counts_exclude_the_point_itself() -> None:
    xyz = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.25, 0, 0], [5.0, 0, 0], [5.0, 0, 0]])
    np.testing.assert_array_equal(neighbor_counts(xyz, radius=0.2), [1, 2, 1, 1, 1])
    np.testing.assert_array_equal(num_neighbors(xyz, radius=0.2, threshold=2), [1, 0, 1, 1, 1])


def test_neighbor_counts_match_brute_force() -> None:
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0, 1.0, (400, 3))
    d = cdist(xyz, xyz)
    expected = (d <= 0.2).sum(axis=1) - 1
    np.testing.assert_array_equal(neighbor_counts(xyz, radius=0.2), expected)
    np.testing.assert_array_equal(num_neighbors(xyz, 0.2, 10), expected < 10)


def test_avg_distances_flags_isolated_points_not_the_plane() -> None:
    plane = _plane()
    far = np.array([[10.0, 10, 5], [-8, 1, 3], [1, -9, 4], [1, 1, 12], [15, -3, 0]])
    xyz = np.vstack([plane, far])
    flags = avg_distances(xyz)  # k = 100, std_ratio = 1
    assert flags.dtype == bool and flags.shape == (len(xyz),)
    assert flags[len(plane) :].all()
    assert not flags[: len(plane)].any()


def test_mean_neighbor_distances_match_brute_force() -> None:
    rng = np.random.default_rng(4)
    xyz = rng.normal(size=(300, 3))
    d = np.sort(cdist(xyz, xyz), axis=1)[:, 1:]  # drop the point itself
    k = 10
    expected_means = d[:, :k].mean(axis=1)
    np.testing.assert_allclose(mean_neighbor_distances(xyz, k=k), expected_means, rtol=1e-9)
    threshold = expected_means.mean() + 0.5 * expected_means.std(ddof=1)
    expected = expected_means > threshold
    assert 0 < expected.sum() < len(xyz)
    np.testing.assert_array_equal(avg_distances(xyz, k=k, std_ratio=0.5), expected)


def test_chunked_equals_unchunked() -> None:
    rng = np.random.default_rng(5)
    xyz = np.vstack([_plane(step=0.05), rng.uniform(-1, 3, (300, 3))])
    whole = len(xyz) + 10
    np.testing.assert_array_equal(
        num_neighbors(xyz, 0.2, 20, chunk_size=37), num_neighbors(xyz, 0.2, 20, chunk_size=whole)
    )
    np.testing.assert_array_equal(
        neighbor_counts(xyz, 0.2, chunk_size=1), neighbor_counts(xyz, 0.2, chunk_size=whole)
    )
    np.testing.assert_array_equal(
        avg_distances(xyz, k=15, chunk_size=37), avg_distances(xyz, k=15, chunk_size=whole)
    )
    np.testing.assert_allclose(
        mean_neighbor_distances(xyz, 15, chunk_size=101),
        mean_neighbor_distances(xyz, 15, chunk_size=whole),
    )


def test_progress_reports_every_chunk() -> None:
    xyz = _plane(step=0.1)  # 400 points
    seen: list[tuple[int, int]] = []
    avg_distances(xyz, k=5, chunk_size=150, progress=lambda done, total: seen.append((done, total)))
    assert seen == [(150, 400), (300, 400), (400, 400)]


def test_small_and_empty_inputs() -> None:
    empty = np.zeros((0, 3))
    assert num_neighbors(empty).shape == (0,)
    assert avg_distances(empty).shape == (0,)
    assert not avg_distances(np.zeros((1, 3))).any()
    # fewer points than k: each averages all the others
    xyz = np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]])
    np.testing.assert_allclose(mean_neighbor_distances(xyz, k=100), [2.0, 1.5, 2.5])


def test_bad_input_is_rejected() -> None:
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        num_neighbors(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        avg_distances(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(ValueError, match="chunk_size"):
        num_neighbors(np.zeros((4, 3)), chunk_size=0)
    with pytest.raises(ValueError, match="k must"):
        avg_distances(np.zeros((4, 3)), k=0)
