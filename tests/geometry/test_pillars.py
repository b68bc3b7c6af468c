"""Pillar grid: stable ids for the same place, round trips, grouping, alignment."""

from __future__ import annotations

import numpy as np
import pytest

from app.geometry.pillars import PillarGrid


def test_cell_index_floors_including_negative() -> None:
    grid = PillarGrid(0.0, 0.0, 0.2)
    xy = np.array([[0.05, 0.05], [0.25, -0.05], [-0.21, 1.0], [3.0, 4.0]])
    np.testing.assert_array_equal(grid.cell_index(xy), [[0, 0], [1, -1], [-2, 5], [15, 20]])
    assert grid.cell_index(xy).dtype == np.int64


def test_cell_index_ignores_z_column() -> None:
    grid = PillarGrid(10.0, -5.0, 0.5)
    xyz = np.array([[10.6, -4.4, 99.0]])
    np.testing.assert_array_equal(grid.cell_index(xyz), [[1, 1]])


def test_ids_are_stable_across_point_sets() -> None:
    grid = PillarGrid(0.0, 0.0, 0.2)
    rng = np.random.default_rng(1)
    place = np.array([[12.31, -7.77]])
    set_a = np.vstack([place, rng.uniform(-50, 50, (1000, 2))])
    set_b = np.vstack([rng.uniform(0, 20, (10, 2)), place])
    id_a = grid.point_cell_ids(set_a)[0]
    id_b = grid.point_cell_ids(set_b)[-1]
    assert id_a == id_b
    # Another point of the same cell, and a fresh grid object with the same parameters, agree.
    assert PillarGrid(0.0, 0.0, 0.2).point_cell_ids(np.array([[12.39, -7.61]]))[0] == id_a


def test_decode_round_trips_including_negative_and_extreme() -> None:
    grid = PillarGrid(0.0, 0.0, 0.2)
    ix = np.array([0, -1, 5, -123456, 2**31 - 1, -(2**31)], dtype=np.int64)
    iy = np.array([0, 7, -3, 987654, -(2**31), 2**31 - 1], dtype=np.int64)
    ids = grid.cell_id(ix, iy)
    assert ids.dtype == np.int64
    assert len(np.unique(ids)) == len(ids)
    dx, dy = grid.decode(ids)
    np.testing.assert_array_equal(dx, ix)
    np.testing.assert_array_equal(dy, iy)
    # The packing is the documented one (as uint64 bits).
    assert int(ids[2].view(np.uint64)) == ((5 + 2**31) << 32) | (-3 + 2**31)
    assert grid.decode(grid.cell_id(-4, 9)) == (-4, 9)


def test_cell_id_rejects_indices_beyond_32_bits() -> None:
    with pytest.raises(ValueError, match="32 bits"):
        PillarGrid(0.0, 0.0, 0.2).cell_id(np.array([2**31]), np.array([0]))


def test_cell_center_is_inside_its_cell() -> None:
    grid = PillarGrid(1.0, -2.0, 0.2)
    centers = grid.cell_center(np.array([0, -3]), np.array([2, 0]))
    np.testing.assert_allclose(centers, [[1.1, -1.5], [0.5, -1.9]])
    np.testing.assert_array_equal(grid.cell_index(centers), [[0, 2], [-3, 0]])


def test_group_counts_points_per_cell() -> None:
    grid = PillarGrid(0.0, 0.0, 1.0)
    xy = np.array([[0.1, 0.1], [0.9, 0.2], [1.5, 0.5], [0.5, 0.5], [-0.5, -0.5]])
    ids, inverse, counts = grid.group(xy)
    assert len(ids) == 3 and counts.sum() == 5
    np.testing.assert_array_equal(ids[inverse], grid.point_cell_ids(xy))
    assert counts[inverse[0]] == 3 and counts[inverse[2]] == 1 and counts[inverse[4]] == 1


def test_aligned_origin_is_a_multiple_of_cell_size() -> None:
    rng = np.random.default_rng(2)
    xy = rng.uniform([456_700.3, 5_400_011.1], [456_800.0, 5_400_100.0], (500, 2))
    grid = PillarGrid.aligned(xy, 0.2)
    assert grid.origin_x <= xy[:, 0].min() and grid.origin_y <= xy[:, 1].min()
    assert round(grid.origin_x / 0.2) * 0.2 == pytest.approx(grid.origin_x, abs=1e-6)
    assert xy[:, 0].min() - grid.origin_x < 0.2
    assert np.all(grid.cell_index(xy) >= 0)
    # Two overlapping tiles aligned separately share cell borders: same centre for the same place.
    other = PillarGrid.aligned(xy[xy[:, 0] > 456_750.0], 0.2)
    p = np.array([[456_760.05, 5_400_050.05]])
    np.testing.assert_allclose(
        grid.cell_center(*grid.cell_index(p).T),
        other.cell_center(*other.cell_index(p).T),
        atol=1e-6,
    )


def test_invalid_cell_size() -> None:
    with pytest.raises(ValueError, match="cell_size"):
        PillarGrid(0.0, 0.0, 0.0)
