"""The labelling view's display tools as functions: colour ramps, the top and side views
rasterised on the server, and the standard views relative to the drive."""

from __future__ import annotations

import numpy as np
import pytest

from app.store.pillar_labels import STORE_GRID
from app.viewer.colour_modes import (
    NO_VALUE_RGB,
    RAMP,
    confidence_colors,
    height_colors,
    intensity_colors,
)
from app.viewer.mini_views import BACKGROUND, HALF_WIDTH, PIXEL, SIDE_ABOVE, side_view, top_view
from app.viewer.modes.pillar_tools import (
    fill_region,
    measure_text,
    pillar_tops,
    points_in_polygon,
)
from app.viewer.view_presets import heading_at, preset_offset


def test_height_ramp_runs_from_blue_on_the_ground_to_red_overhead() -> None:
    rgb = height_colors(np.array([-5.0, 0.0, 4.0, 50.0, np.nan]))
    assert tuple(rgb[0]) == tuple(RAMP[0]) and tuple(rgb[3]) == tuple(RAMP[-1])  # clamped
    assert rgb[1, 2] > rgb[1, 0] and rgb[2, 1] > rgb[2, 2]  # bluish low, greener higher
    assert tuple(rgb[4]) == tuple(NO_VALUE_RGB)
    assert rgb.max(axis=1).min() < 250  # no near-white on the white background


def test_intensity_is_a_grey_ramp_between_percentiles_and_grey_without() -> None:
    value = np.r_[np.linspace(0.0, 1.0, 101), np.nan]
    rgb = intensity_colors(value)
    assert (rgb[:-1, 0] == rgb[:-1, 1]).all() and (np.diff(rgb[:-1, 0].astype(int)) >= 0).all()
    assert rgb[0, 0] < 60 and 180 < rgb[-2, 0] < 250
    assert tuple(rgb[-1]) == tuple(NO_VALUE_RGB)
    assert (intensity_colors(np.full(3, np.nan)) == NO_VALUE_RGB).all()  # none recorded


def test_confidence_is_red_when_unsure_green_when_sure() -> None:
    rgb = confidence_colors(np.array([0.2, 1.0, np.nan]))
    assert rgb[0, 0] > 2 * rgb[0, 1] and rgb[1, 1] > 2 * rgb[1, 0]
    assert tuple(rgb[2]) == tuple(NO_VALUE_RGB)


def test_top_view_puts_ahead_up_and_keeps_the_highest_point() -> None:
    heading = np.array([0.0, 1.0])  # driving north: north is up, east is right
    xyz = np.array([[0.0, 5.0, 0.0], [3.0, 0.0, 0.0], [3.0, 0.0, 2.0]])
    rgb = np.array([(10, 10, 10), (20, 20, 20), (30, 30, 30)], dtype=np.uint8)
    image = top_view(xyz, rgb, np.zeros(3), heading)
    size = int(round(2 * HALF_WIDTH / PIXEL))
    assert image.shape == (size, size, 3)
    centre = size // 2
    assert tuple(image[centre - 50, centre]) == (10, 10, 10)  # 5 m ahead: 50 px up
    assert tuple(image[centre, centre + 30]) == (30, 30, 30)  # 3 m east: right, the top one
    assert (image == BACKGROUND).all(axis=2).mean() > 0.99


def test_side_view_shows_the_slab_nearest_the_viewer_on_the_right() -> None:
    heading = np.array([1.0, 0.0])  # driving east: the right of the drive is south
    xyz = np.array(
        [
            [2.0, -1.0, 1.0],  # in the slab, nearer the viewer (south)
            [2.0, 1.0, 1.0],  # in the slab, behind it: hidden
            [6.0, 8.0, 1.0],  # outside the slab: not drawn
        ]
    )
    rgb = np.array([(10, 10, 10), (20, 20, 20), (30, 30, 30)], dtype=np.uint8)
    image = side_view(xyz, rgb, np.zeros(3), heading)
    row = int(round(SIDE_ABOVE / PIXEL)) - 10  # 1 m above the focus
    col = int(round(HALF_WIDTH / PIXEL)) + 20  # 2 m ahead: right of the centre
    assert tuple(image[row, col]) == (10, 10, 10)
    assert not (image == 30).all(axis=2).any()


def test_heading_follows_the_nearest_trajectory_segment() -> None:
    trajectory = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0]], dtype=float)
    np.testing.assert_allclose(heading_at(trajectory, np.array([5.0, 1.0])), [1.0, 0.0])
    np.testing.assert_allclose(heading_at(trajectory, np.array([11.0, 6.0])), [0.0, 1.0])
    np.testing.assert_allclose(heading_at(np.zeros((1, 3)), np.zeros(2)), [1.0, 0.0])


def test_presets_look_down_along_and_across_the_drive() -> None:
    heading = np.array([0.0, 1.0])
    top = preset_offset("Top", heading, 40.0)
    front = preset_offset("Front", heading, 40.0)
    side = preset_offset("Side", heading, 40.0)
    for offset in (top, front, side):
        assert np.linalg.norm(offset) == pytest.approx(40.0)
    assert top[2] > 39.0  # from above
    assert front[1] < -39.0  # from behind, looking ahead
    assert side[0] > 39.0  # from the right (east of a northbound drive)
    oblique = preset_offset("Oblique", heading, 40.0)
    assert oblique[2] > 0 and oblique[1] < 0
    assert np.linalg.norm(preset_offset("Top", heading, 1e6)) == pytest.approx(300.0)
    with pytest.raises(ValueError, match="unknown view"):
        preset_offset("Bottom", heading, 10.0)


def test_pillar_tops_are_the_highest_point_of_each_pillar_holding_points() -> None:
    cells = np.array([10, 20, 30, 40], dtype=np.int64)  # the map's sorted pillars
    pillar = np.array([3, 1, 3, 3, 1])  # points in pillars 40 and 20; none in 10 or 30
    z = np.array([0.5, -1.0, 2.0, 1.0, -2.0], dtype=np.float32)
    found, top = pillar_tops(cells, pillar, z)
    assert found.tolist() == [20, 40] and top.tolist() == [-1.0, 2.0]


def test_fill_takes_the_sloping_road_and_stops_at_the_kerb_and_the_car() -> None:
    ix, iy = np.meshgrid(np.arange(1000, 1050), np.arange(2000, 2030), indexing="ij")
    ix, iy = ix.ravel(), iy.ravel()
    top = 0.01 * (ix - 1000)  # a 5 % slope along x (1 cm per 0.2 m pillar)
    sidewalk = iy >= 2020
    top = top + np.where(sidewalk, 0.15, 0.0)  # a 15 cm kerb
    car = (ix >= 1020) & (ix < 1030) & (iy >= 2005) & (iy < 2012)
    top[car] += 1.5
    cells = np.asarray(STORE_GRID.cell_id(ix, iy), dtype=np.int64)
    order = np.argsort(cells)
    cells, top, sidewalk, car = cells[order], top[order], sidewalk[order], car[order]
    seed = int(cells[np.flatnonzero(~sidewalk & ~car)[0]])
    filled = fill_region(cells, top, seed)
    expected = cells[~sidewalk & ~car]
    assert np.array_equal(np.sort(filled), np.sort(expected))
    assert len(fill_region(cells, top, int(cells[np.flatnonzero(car)[0]]))) == car.sum()
    assert len(fill_region(cells, top, -1)) == 0  # a seed without a pillar


def test_polygon_contains_by_the_even_odd_rule() -> None:
    square = np.array([[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]])
    uv = np.array([[0.5, 0.5], [0.1, 0.5], [0.79, 0.21], [0.9, 0.9]])
    assert points_in_polygon(uv, square).tolist() == [True, False, True, False]
    bowtie_notch = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.5, 0.2], [0.0, 1.0]])
    assert points_in_polygon(np.array([[0.5, 0.6], [0.5, 0.1]]), bowtie_notch).tolist() == [
        False,
        True,
    ]


def test_polygon_test_of_a_free_hand_loop_matches_the_edge_by_edge_rule() -> None:
    """A lasso's hundreds of edges, points on whole pixel rows and on its vertices' rows: the
    row-sorted test gives what testing every point against every edge gives."""
    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 1000, (20_000, 2))
    uv[:500] = np.round(uv[:500])
    t = np.linspace(0, 6, 200)
    loop = np.round(np.stack([500 + 300 * np.cos(t) + rng.normal(0, 20, 200),
                              500 + 300 * np.sin(2 * t)], axis=1))  # fmt: skip
    u, v = uv[:, 0], uv[:, 1]
    expected = np.zeros(len(uv), dtype=bool)
    for a, b in zip(loop, np.roll(loop, -1, axis=0), strict=True):
        crosses = (a[1] > v) != (b[1] > v)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = a[0] + (v - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
        expected ^= crosses & (u < x)
    assert 3_000 < expected.sum() < 17_000
    assert np.array_equal(points_in_polygon(uv, loop), expected)


def test_measure_reports_3d_horizontal_and_vertical() -> None:
    text = measure_text(np.array([0.0, 0.0, 0.0]), np.array([3.0, 4.0, -12.0]))
    assert "**13.00 m**" in text and "horizontal 5.00 m" in text and "vertical -12.00 m" in text
