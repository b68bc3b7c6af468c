"""The simulated road: long surveys bend as streets do and never pass their own street twice."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from app.simulate.road import MAX_BEND, STATION_STEP, Centerline, RoadProfile, bends


def test_a_short_curve_stays_one_curve():
    assert bends(40.0, 90.0, 1 / 150.0) == ((40.0, 90.0, 1 / 150.0),)


@pytest.mark.parametrize("curvature", [1 / 120.0, -1 / 300.0])
def test_a_long_curve_becomes_bends_turning_left_and_right(curvature):
    curves = bends(1600.0, 3600.0, curvature)
    assert curves[0][0] == 1600.0 and curves[-1][1] == 3600.0
    for (_, end, k), (start, _, k_next) in zip(curves[:-1], curves[1:], strict=True):
        assert end == pytest.approx(start) and k_next == -k
    assert all((end - start) * abs(k) <= MAX_BEND + 1e-9 for start, end, k in curves)


def test_a_4_km_road_at_a_city_radius_never_comes_back_along_itself():
    """Before bends, 2 km at 1/120 m circled 2.6 times over its own street (a survey's way out
    and back, which made a long survey cost more per km than a short one)."""
    profile = RoadProfile(4000.0, curves=bends(1600.0, 3600.0, 1 / 120.0))
    line = Centerline.from_profile(profile)
    heading = line.heading - line.heading[0]
    step = STATION_STEP / 120.0  # the heading is sampled every station step
    assert heading.min() >= -step and heading.max() <= MAX_BEND + step
    pairs = cKDTree(line.xyz[:, :2]).query_pairs(100.0, output_type="ndarray")
    apart = np.abs(line.stations[pairs[:, 0]] - line.stations[pairs[:, 1]])
    assert not np.any(apart > 150.0)
