"""Tiles along the trajectory: stations, ownership, and the spatial halo."""

from __future__ import annotations

import numpy as np
import pytest

from app.geometry.tiles import TileLayout, cell_indices, cell_keys, halo_cells


def _bend() -> np.ndarray:
    """100 m east, then a right angle and 50 m north, sampled every metre (with a stop)."""
    east = np.column_stack([np.arange(0.0, 100.0), np.zeros(100)])
    north = np.column_stack([np.full(51, 100.0), np.arange(0.0, 51.0)])
    return np.vstack([east, east[-1:], north])  # the repeated position is a stop


def test_stations_are_the_arc_length_at_the_foot_of_each_point() -> None:
    layout = TileLayout.along(_bend(), length=40.0, halo=5.0)
    assert layout.total == pytest.approx(150.0) and layout.count == 4
    points = np.array([[10.3, 4.0], [10.3, -7.0], [103.0, 20.5], [-3.0, 1.0], [100.0, 60.0]])
    np.testing.assert_allclose(layout.stations(points), [10.3, 10.3, 120.5, -3.0, 160.0])
    owner = layout.owner(layout.stations(points))
    assert owner.tolist() == [0, 0, 3, 0, 3]  # before the start and past the end: end tiles
    assert layout.bounds(0) == (-np.inf, 40.0) and layout.bounds(1) == (40.0, 80.0)
    with pytest.raises(IndexError):
        layout.bounds(4)


def test_dense_stretches_get_shorter_tiles() -> None:
    """1,000 points per metre on the first 100 m, 10,000 per metre after: tiles of at most
    40 m whose window (the tile and 5 m each side) holds at most about 50,000 points; where
    the halo alone holds more, tiles are as short as they may be (2 m)."""
    layout = TileLayout.along(_bend(), length=40.0, halo=5.0)
    station = np.arange(0.0, 150.0, 0.5) + 0.25
    points = np.where(station < 100.0, 500, 5000)
    cut = layout.cut_by_points(station, points, max_points=50_000, min_length=2.0)
    edges = np.asarray(cut.edges)
    assert edges[0] == 0.0 and np.all(np.diff(edges) <= 40.0) and np.all(np.diff(edges) >= 2.0)
    assert edges[1] == pytest.approx(40.0)  # sparse: the length decides
    for start, end in zip(edges, np.r_[edges[1:], cut.total], strict=True):
        window = (station >= start - 5.0) & (station < end + 5.0)
        assert points[window].sum() <= 50_000 + 5000 or end - start == pytest.approx(2.0)
    assert np.diff(edges)[-1] < 10.0  # dense: the points decide
    assert cut.owner(np.array([1.0, 41.0, cut.total])).tolist() == [0, 1, cut.count - 1]
    assert layout.cut_by_points(station, points, 10**9, 2.0).edges == layout.edges


def test_tiles_are_evened_over_the_workers() -> None:
    """150 m in tiles of 40 m is 4 tiles (40, 40, 40, 30); on 3 workers the nearest multiple
    (3) of 50 m, on 8 workers 8 of 18.75 m (at least one multiple), on 2 workers 4 equal
    tiles; half-way between two multiples, the fewer tiles. Never more than EVEN_STRETCH
    times the length, and one tile stays one whatever the workers."""
    from app.geometry.tiles import EVEN_STRETCH

    for workers, count in ((1, 4), (2, 4), (3, 3), (5, 5), (8, 8)):
        layout = TileLayout.along(_bend(), length=40.0, halo=5.0, workers=workers)
        assert layout.count == count, workers
        sizes = np.diff([*layout.edges, layout.total])
        np.testing.assert_allclose(sizes, 150.0 / count)
        assert layout.length == pytest.approx(150.0 / count)
        assert layout.length <= EVEN_STRETCH * 40.0
    assert TileLayout.along(_bend(), length=200.0, halo=5.0, workers=2).count == 1
    assert TileLayout.along(_bend(), length=30.0, halo=5.0, workers=2).count == 4  # 5: 4 or 6
    # a layout evened first is cut by points with its own length (the cut keeps its edges)
    even = TileLayout.along(_bend(), length=40.0, halo=5.0, workers=3)
    assert even.cut_by_points(np.zeros(1), np.ones(1), 10**9, 2.0).edges == even.edges
    # the worst case: just under 3 lengths on 2 workers is 2 tiles of 1.5 lengths at most
    assert TileLayout.along(_bend(), length=50.01, halo=5.0, workers=2).length <= 75.0 + 1e-9


def test_balanced_tiles_hold_the_same_work() -> None:
    """Two tiles of 75 m over a street whose first 60 m cost three times what the rest does
    (a built-up stretch, then open road): the edge moves back so that both windows (tile and
    5 m halo) hold the same cost, within a sample's cost; a tile never grows past the longest
    allowed, and where that cannot cover the trajectory the layout stays as it was."""
    layout = TileLayout.along(_bend(), length=100.0, halo=5.0, workers=2)
    assert layout.edges == (0.0, 75.0)
    station = np.arange(0.0, 150.0, 0.5) + 0.25
    cost = np.where(station < 60.0, 3.0, 1.0)
    balanced = layout.balanced(station, cost, max_length=150.0)
    assert balanced.count == 2 and balanced.halo == layout.halo
    edge = balanced.edges[1]
    assert 40.0 < edge < 75.0
    windows = [(station < edge + 5.0), (station >= edge - 5.0)]
    held = [cost[w].sum() for w in windows]
    assert abs(held[0] - held[1]) <= 3.0 + 1e-9
    assert balanced.owner(np.array([edge - 0.1, edge + 0.1])).tolist() == [0, 1]
    assert layout.balanced(station, np.ones_like(station), 150.0).edges[1] == pytest.approx(
        75.0, abs=0.5
    )  # even cost: the edges stay about where they were
    assert layout.balanced(station, cost, max_length=80.0).edges[1] >= 70.0  # capped
    assert layout.balanced(station, cost, max_length=60.0).edges == layout.edges
    one = TileLayout.along(_bend(), length=200.0, halo=5.0)
    assert one.balanced(station, cost, 300.0) is one


def test_bad_layouts_are_refused() -> None:
    with pytest.raises(ValueError, match="tile length"):
        TileLayout.along(_bend(), length=0.0, halo=1.0)
    with pytest.raises(ValueError, match="at least one position"):
        TileLayout.along(np.zeros((0, 3)), length=10.0, halo=1.0)


def test_cell_keys_round_trip_and_the_halo_covers_its_radius() -> None:
    xy = np.array([[0.5, 0.5], [-0.5, 3.9], [4_500_000.2, -5_300_000.7]])  # UTM-sized too
    i, j = cell_indices(cell_keys(xy, 2.0))
    assert i.tolist() == [0, -1, 2_250_000] and j.tolist() == [0, 1, -2_650_001]
    own = cell_keys(np.array([[0.5, 0.5]]), 2.0)
    halo = halo_cells(own, 3.0, 2.0)  # ceil(3 / 2) = 2 cells each way: 5 x 5
    assert len(halo) == 25
    rng = np.random.default_rng(0)
    near = rng.uniform(-3.0, 3.0, (1000, 2)) + [1.0, 1.0]  # within 3 m of the cell
    assert np.isin(cell_keys(near, 2.0), halo).all()
