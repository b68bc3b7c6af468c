"""Trajectory: arc length, resampling, tangents, slicing planes, stations and lateral offsets."""

from __future__ import annotations

import numpy as np
import pytest

from app.geometry.trajectory import (
    StationIndex,
    arc_length,
    resample,
    slice_index,
    slicing_planes,
    station_offsets,
    tangents,
    total_length,
)

R = 50.0
ORIGIN = np.array([456_000.0, 5_400_000.0, 120.0])  # UTM-sized coordinates


def _straight(n: int = 101, length: float = 100.0) -> np.ndarray:
    """Along +x from ORIGIN."""
    x = np.linspace(0.0, length, n)
    return ORIGIN + np.stack([x, np.zeros(n), np.zeros(n)], axis=1)


def _circle(n: int = 2001, turns: float = 0.75) -> np.ndarray:
    """Counter-clockwise arc of radius R about ORIGIN, starting at angle 0."""
    theta = np.linspace(0.0, 2 * np.pi * turns, n)
    return ORIGIN + np.stack([R * np.cos(theta), R * np.sin(theta), np.zeros(n)], axis=1)


def test_arc_length_straight_line() -> None:
    pos = _straight()
    s = arc_length(pos)
    assert s[0] == 0.0
    np.testing.assert_allclose(s, np.linspace(0, 100, 101), atol=1e-9)
    assert total_length(pos) == pytest.approx(100.0)


def test_arc_length_circle() -> None:
    # A polygon with 2000 chords over 3/4 of the circle is within 1e-5 relative of the arc.
    assert total_length(_circle()) == pytest.approx(2 * np.pi * R * 0.75, rel=1e-5)


def test_resample_even_spacing() -> None:
    pos = _straight(n=7, length=10.0)
    out = resample(pos, 0.3)
    assert len(out) == 34  # 0, 0.3, ..., 9.9
    np.testing.assert_allclose(np.diff(out[:, 0]), 0.3, atol=1e-9)
    np.testing.assert_allclose(out[:, 1:], np.tile(ORIGIN[1:], (34, 1)))
    circle = resample(_circle(), 1.0)
    np.testing.assert_allclose(np.linalg.norm(np.diff(circle, axis=0), axis=1), 1.0, atol=1e-4)


def test_tangents_circle_are_unit_horizontal_and_tangent() -> None:
    pos = _circle()
    t = tangents(pos)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0)
    assert np.all(t[:, 2] == 0.0)
    theta = np.linspace(0.0, 1.5 * np.pi, len(pos))
    expected = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    np.testing.assert_allclose(t[1:-1, :2], expected[1:-1], atol=1e-7)
    np.testing.assert_allclose(t[[0, -1], :2], expected[[0, -1]], atol=2e-3)  # one-sided ends


def test_stopped_vehicle_gives_no_nan() -> None:
    base = _straight(n=11, length=10.0)
    pos = np.vstack([base[:5], np.repeat(base[5:6], 20, axis=0), base[5:], base[-1:], base[-1:]])
    pos[:, 2] += np.linspace(0, 0.5, len(pos))  # a gentle climb while driving and stopping
    t = tangents(pos)
    assert np.all(np.isfinite(t))
    np.testing.assert_allclose(t, np.tile([1.0, 0.0, 0.0], (len(pos), 1)), atol=1e-12)
    planes = slicing_planes(pos, 0.5)
    assert np.all(np.isfinite(planes.normals)) and np.all(np.isfinite(planes.origins))
    station, lateral = station_offsets(ORIGIN + np.array([[5.0, 2.0, 0.0]]), pos)
    assert np.all(np.isfinite(station)) and lateral[0] == pytest.approx(2.0)


def test_stationary_trajectory_is_rejected() -> None:
    with pytest.raises(ValueError, match="no horizontal extent"):
        tangents(np.repeat(ORIGIN[None], 5, axis=0))


def test_slicing_planes_straight_line() -> None:
    planes = slicing_planes(_straight(n=21, length=20.0), 0.5)
    assert len(planes.stations) == 41
    np.testing.assert_allclose(planes.stations, np.arange(41) * 0.5)
    np.testing.assert_allclose(planes.origins[:, 0] - ORIGIN[0], planes.stations, atol=1e-9)
    np.testing.assert_allclose(planes.normals, np.tile([1.0, 0.0, 0.0], (41, 1)), atol=1e-12)


def test_slicing_planes_circle_every_half_metre_with_tangent_normals() -> None:
    planes = slicing_planes(_circle(), 0.5)
    assert len(planes.stations) == int(total_length(_circle()) / 0.5) + 1  # 0 .. 235.5 m
    np.testing.assert_allclose(np.diff(planes.stations), 0.5)
    np.testing.assert_allclose(np.linalg.norm(planes.normals, axis=1), 1.0)
    assert np.all(planes.normals[:, 2] == 0.0)
    radial = planes.origins[:, :2] - ORIGIN[:2]
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    # Normals are perpendicular to the radius (tangent) and point counter-clockwise.
    assert np.max(np.abs(np.sum(planes.normals[:, :2] * radial, axis=1))) < 2e-3
    cross = radial[:, 0] * planes.normals[:, 1] - radial[:, 1] * planes.normals[:, 0]
    assert np.all(cross > 0.999)
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), 1.0)
    np.testing.assert_allclose(
        np.linalg.norm(planes.origins[:, :2] - ORIGIN[:2], axis=1), R, atol=1e-3
    )


def test_station_offsets_straight_line() -> None:
    pos = _straight()
    rng = np.random.default_rng(4)
    along = rng.uniform(0, 100, 5000)
    side = rng.uniform(-10, 10, 5000)
    xyz = ORIGIN + np.stack([along, side, rng.uniform(-2, 3, 5000)], axis=1)
    station, lateral = station_offsets(xyz, pos)
    np.testing.assert_allclose(station, along, atol=0.05)
    np.testing.assert_allclose(lateral, side, atol=1e-6)  # +y is left of a drive along +x


def test_station_offsets_circle_and_lateral_sign() -> None:
    pos = _circle()
    rng = np.random.default_rng(5)
    theta = rng.uniform(0.01, 1.5 * np.pi - 0.01, 4000)
    offset = rng.uniform(-8, 8, 4000)  # positive: towards the centre, which is left of a CCW drive
    r = R - offset
    xyz = ORIGIN + np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros_like(r)], axis=1)
    station, lateral = station_offsets(xyz, pos)
    np.testing.assert_allclose(station, R * theta, atol=0.05)
    np.testing.assert_allclose(lateral, offset, atol=0.01)
    assert np.all(np.sign(lateral) == np.sign(offset))


def test_slice_index_every_half_metre() -> None:
    pos = _straight(n=11, length=10.0)
    xyz = ORIGIN + np.array([[0.1, 3.0, 0.0], [0.6, -2.0, 1.0], [7.26, 0.0, 0.0], [9.99, 1.0, 0.0]])
    np.testing.assert_array_equal(slice_index(xyz, pos, 0.5), [0, 1, 14, 19])
    assert slice_index(xyz, pos, 0.5).dtype == np.int64


def test_station_far_to_the_side_of_a_curve() -> None:
    # Points 25 m off a 50 m radius curve, both sides, away from the one-sided ends.
    pos = _circle()
    theta = np.linspace(0.1, 1.4 * np.pi, 500)
    for offset in (25.0, -25.0):
        r = R - offset
        xyz = ORIGIN + np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros_like(theta)], 1)
        station, lateral = station_offsets(xyz, pos)
        np.testing.assert_allclose(station, R * theta, atol=0.05)
        np.testing.assert_allclose(lateral, offset, atol=0.01)


def test_station_index_reused_and_beyond_the_ends() -> None:
    pos = _straight(n=11, length=10.0)
    index = StationIndex(pos)
    xyz = ORIGIN + np.array([[-2.0, 1.0, 0.0], [12.5, -1.0, 0.0], [4.321, 0.5, 0.0]])
    station, lateral = index.query(xyz)
    np.testing.assert_allclose(station, [-2.0, 12.5, 4.321], atol=1e-9)
    np.testing.assert_allclose(lateral, [1.0, -1.0, 0.5], atol=1e-9)
    again, _ = station_offsets(xyz, pos)
    np.testing.assert_array_equal(again, station)
    empty_station, empty_lateral = index.query(np.zeros((0, 3)))
    assert empty_station.shape == (0,) and empty_lateral.shape == (0,)
