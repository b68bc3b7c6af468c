"""Guardrail segmentation: road removal, lattice components, slices, crops, features, correction.

Survey-based tests use frames 8-33 (about 26 m) of the shipped sample `data_samples/urban-60m`
(simulated profile scanner and camera, a pipe guardrail on the right from x = 12 m, parked cars
right before it, a beam guardrail on the left from x = 27 m).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.geometry.projection import project
from app.io.registry import open_survey
from app.pipelines.guardrail.components import connected_components
from app.pipelines.guardrail.correction import correct_labels
from app.pipelines.guardrail.crops import slice_crops
from app.pipelines.guardrail.features import FEATURE_NAMES, slice_features
from app.pipelines.guardrail.road import remove_road, road_removal
from app.pipelines.guardrail.scan_points import (
    ScanPoints,
    load_scan_points,
    profile_lattice,
    rings_from_elevation,
    rings_from_order,
)
from app.pipelines.guardrail.slices import cut_slices

SAMPLE = Path(__file__).resolve().parents[3] / "data_samples" / "urban-60m"
FRAMES = list(range(8, 34))
ROAD, CAR, BUILDING = 40, 10, 50


@pytest.fixture(scope="module")
def segmented():
    """The sample's frames 8-33 through road removal, components and slices."""
    if not SAMPLE.is_dir():
        pytest.skip("data_samples/urban-60m is missing")
    survey = open_survey(SAMPLE, "sim")
    points = load_scan_points(survey, frames=FRAMES)
    refs = [survey.frames[i].reference_labels() for i in FRAMES]
    truth = {k: np.concatenate([r[k] for r in refs]) for k in ("guardrail", "semantic")}
    traj = survey.poses()
    road = road_removal(points.xyz, traj)
    comps = connected_components(points, road.keep, above_ground=road.above_ground)
    slices = cut_slices(points.xyz, comps.label, traj, min_points=5)
    return survey, points, truth, road, comps, slices


def _main_component(label: np.ndarray, mask: np.ndarray) -> int:
    values, counts = np.unique(label[mask & (label >= 0)], return_counts=True)
    return int(values[np.argmax(counts)])


# ------------------------------------------------------------------------------ road removal


def test_road_removal_keeps_guardrails_and_drops_the_road(segmented):
    _, points, truth, road, _, _ = segmented
    guardrail = truth["guardrail"] >= 0
    assert guardrail.sum() > 1000
    assert road.keep[guardrail].mean() > 0.97
    assert (~road.keep[truth["semantic"] == ROAD]).mean() > 0.97
    assert (~road.keep[truth["semantic"] == BUILDING]).mean() > 0.95  # beyond the road edge
    # the simulated scanner is 2.4 m above the road: measured, not assumed
    assert road.model.mount_height == pytest.approx(2.4, abs=0.05)


def test_remove_road_on_a_sloped_road_with_a_wall():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 30, 60_000)
    y = rng.uniform(-6, 6, 60_000)
    z = 0.05 * x + rng.normal(0, 0.005, len(x))  # 5 % grade: a constant height would fail
    wall_x = rng.uniform(0, 30, 8000)
    wall_z = rng.uniform(0.0, 1.0, 8000) + 0.05 * wall_x
    wall = np.column_stack([wall_x, np.full(8000, 3.0) + rng.normal(0, 0.005, 8000), wall_z])
    far = np.column_stack([rng.uniform(0, 30, 2000), np.full(2000, 30.0), rng.uniform(0, 3, 2000)])
    xyz = np.vstack([np.column_stack([x, y, z]), wall, far])
    t = np.linspace(0, 30, 61)
    traj = np.column_stack([t, np.zeros_like(t), 0.05 * t + 2.0])
    keep = remove_road(xyz, traj, max_lateral=15.0)
    assert keep.dtype == bool and keep.shape == (len(xyz),)
    n = len(x)
    assert (~keep[:n]).mean() > 0.98  # road
    assert keep[n : n + 8000].mean() > 0.95  # wall
    assert not keep[n + 8000 :].any()  # 30 m away


# -------------------------------------------------------------------------------- components


def test_components_separate_guardrail_from_parked_car(segmented):
    _, points, truth, road, comps, _ = segmented
    assert comps.method == "lattice"
    pipe = truth["guardrail"] == 0
    label = comps.label
    main = _main_component(label, pipe)
    assert (label[pipe] == main).mean() > 0.9  # the pipe guardrail is one component
    in_main = label == main
    # anything else in it is ground under the rail, attached as a low point (< 0.25 m)
    other = in_main & (truth["guardrail"] != 0)
    assert (road.above_ground[other] < 0.25).all()
    car = (truth["semantic"] == CAR) & road.keep
    assert car.sum() > 1000
    assert not (in_main & car).any()
    assert _main_component(label, car) != main


def test_profile_lattice_from_times():
    profile = np.repeat(np.arange(5), 3000)
    step = np.tile(np.arange(3000), 5)
    t = 1e9 + profile / 100.0 + step / 300_000.0  # GPS-sized seconds
    lat = profile_lattice(t)
    assert np.array_equal(lat.row - lat.row[0], profile)
    assert np.array_equal(lat.col, step)


def test_rotating_rings_from_order_and_elevation():
    elev = np.linspace(2.0, -24.8, 64)
    az = np.linspace(0.0, 2 * np.pi, 500, endpoint=False)
    # ring-major like KITTI .bin: each ring one sweep starting facing forward (azimuth >= 0)
    ring = np.repeat(np.arange(64), 500)
    a = np.tile(az, 64)
    a = np.where(a > np.pi, a - 2 * np.pi, a)
    e = np.radians(elev[ring])
    xyz = 10.0 * np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    assert np.array_equal(rings_from_order(xyz), ring)
    assert np.array_equal(rings_from_elevation(xyz, elev), ring)
    column_major = xyz.reshape(64, 500, 3).transpose(1, 0, 2).reshape(-1, 3)
    assert rings_from_order(column_major) is None  # not ring-major: use the elevation


def test_euclidean_fallback_without_lattice():
    rng = np.random.default_rng(1)
    a = rng.normal(0, 0.1, (2000, 3))
    b = rng.normal(0, 0.1, (2000, 3)) + [2.0, 0, 0]
    comps = connected_components(np.vstack([a, b]), min_points=1)
    assert comps.method == "euclidean"
    assert len(np.unique(comps.label[:2000])) == 1
    assert comps.label[0] != comps.label[-1]


# ------------------------------------------------------------------------------------ slices


def test_slices_are_half_a_metre_along_a_curved_trajectory():
    s = np.linspace(0, 30, 301)
    radius = 40.0
    traj = np.column_stack([radius * np.sin(s / radius), radius * (1 - np.cos(s / radius)), s * 0])
    arc = np.random.default_rng(2).uniform(0, 30, 5000)
    r = radius - 4.0  # a rail 4 m to the left of the curve
    xyz = np.column_stack(
        [r * np.sin(arc / radius), radius - r * np.cos(arc / radius), np.full(len(arc), 0.8)]
    )
    component = np.zeros(len(xyz), dtype=np.int64)
    slices = cut_slices(xyz, component, traj, spacing=0.5)
    assert len(slices) == 60
    assert np.array_equal(slices.station_index, np.arange(60))
    st = slices.point_station
    assert np.allclose(st, arc, atol=0.02)  # stations follow the arc length
    for k in range(len(slices)):
        pts = slices.points(k)
        assert st[pts].min() >= 0.5 * k - 1e-9 and st[pts].max() < 0.5 * (k + 1) + 1e-9
    assert (slices.side == 1).all()
    assert np.allclose(slices.lateral, 4.0, atol=0.02)


def test_sample_slices(segmented):
    _, points, truth, _, comps, slices = segmented
    pipe_slices = np.unique(
        slices.point_slice[(truth["guardrail"] == 0) & (slices.point_slice >= 0)]
    )
    assert len(pipe_slices) > 30
    assert (slices.side[pipe_slices] == -1).mean() > 0.9  # right of the drive
    extent = np.array([np.ptp(slices.point_station[slices.points(k)]) for k in pipe_slices])
    assert extent.max() < 0.5


# ------------------------------------------------------------------------------------- crops


def test_crops_contain_the_slice_and_use_the_largest_rectangle(segmented):
    survey, points, truth, _, _, slices = segmented
    guardrail = truth["guardrail"] >= 0
    frac = (
        np.bincount(
            slices.point_slice[slices.point_slice >= 0],
            guardrail[slices.point_slice >= 0],
            minlength=len(slices),
        )
        / slices.counts
    )
    chosen = np.flatnonzero(frac > 0.5)[::4]
    crops = slice_crops(survey, slices, points.xyz, slices=chosen)
    assert len(crops) >= 0.8 * len(chosen)
    cam = survey.cameras["image_02"]
    poses = survey.poses()
    for crop in crops[:6]:
        pts = points.xyz[slices.points(crop.slice)]
        T = cam.T_cam_sensor @ np.linalg.inv(poses[crop.frame])
        proj = project(pts, cam.P, T, cam.width, cam.height, min_depth=1.0)
        assert proj.in_image.all()
        u0, v0, u1, v1 = crop.box
        assert (proj.uv[:, 0] >= u0).all() and (proj.uv[:, 0] < u1).all()
        assert (proj.uv[:, 1] >= v0).all() and (proj.uv[:, 1] < v1).all()
        assert crop.image.shape == (v1 - v0, u1 - u0, 3) and crop.image.dtype == np.uint8
        assert crop.resized().shape == (224, 224, 3)
        # brute force over every frame: no image holding all points has a larger rectangle
        areas = []
        for f in range(len(survey)):
            Tf = cam.T_cam_sensor @ np.linalg.inv(poses[f])
            p = project(pts, cam.P, Tf, cam.width, cam.height, min_depth=1.0)
            if p.in_image.all():
                areas.append(np.ptp(p.uv[:, 0]) * np.ptp(p.uv[:, 1]))
        assert crop.area == pytest.approx(max(areas))


# ---------------------------------------------------------------------------------- features


def _beam_and_trunk():
    """Ground, a 0.3 m beam at 0.6-0.9 m along x (4 m left), a trunk 3 m tall (4 m right)."""
    rng = np.random.default_rng(3)
    ground = np.column_stack(
        [rng.uniform(0, 20, 40_000), rng.uniform(-8, 8, 40_000), rng.normal(0, 0.01, 40_000)]
    )
    beam = np.column_stack(
        [rng.uniform(2, 18, 8000), 4.0 + rng.normal(0, 0.01, 8000), rng.uniform(0.6, 0.9, 8000)]
    )
    phi = rng.uniform(0, 2 * np.pi, 3000)
    trunk = np.column_stack(
        [10.2 + 0.15 * np.cos(phi), -4.0 + 0.15 * np.sin(phi), rng.uniform(0, 3.0, 3000)]
    )
    xyz = np.vstack([ground, beam, trunk])
    component = np.concatenate(
        [np.full(len(ground), -1), np.zeros(len(beam)), np.ones(len(trunk))]
    ).astype(np.int64)
    traj = np.column_stack([np.linspace(0, 20, 41), np.zeros(41), np.full(41, 2.0)])
    return xyz, component, traj


def test_features_tell_a_guardrail_from_a_tree_trunk():
    xyz, component, traj = _beam_and_trunk()
    slices = cut_slices(xyz, component, traj)
    features, names = slice_features(xyz, slices)
    assert names == FEATURE_NAMES
    assert features.shape == (len(slices), len(FEATURE_NAMES)) and features.dtype == np.float32
    assert np.isfinite(features).all()
    col = {n: features[:, i] for i, n in enumerate(names)}
    beam = (slices.component == 0) & (slices.station > 3) & (slices.station < 17)
    trunk = slices.component == 1
    assert beam.sum() > 20 and trunk.sum() == 1
    assert np.allclose(col["height_max"][beam], 0.9, atol=0.05)
    assert np.allclose(col["height_min"][beam], 0.6, atol=0.05)
    assert (col["along_alignment"][beam] > 0.95).all()
    assert (col["linearity"][beam] > 0.8).all()
    assert np.allclose(col["lateral"][beam], 4.0, atol=0.05)
    assert (col["extent_along"][beam] <= 0.5).all()
    assert col["height_max"][trunk][0] > 2.8
    assert col["verticality"][trunk][0] > 0.95
    assert col["along_alignment"][trunk][0] < 0.3
    assert col["abs_lateral"][trunk][0] == pytest.approx(4.0, abs=0.2)


# -------------------------------------------------------------------------------- correction


def _chains():
    """Component 0: 12 consecutive slices on the left; component 1: 4 slices on the right."""
    station = np.concatenate([np.arange(12), np.arange(4)]) * 0.5 + 0.25
    lateral = np.concatenate([np.full(12, 4.0), np.full(4, -4.0)])
    xyz = np.column_stack([station, lateral, np.full(16, 0.8)])
    traj = np.column_stack([np.linspace(0, 10, 21), np.zeros(21), np.full(21, 2.0)])
    component = np.concatenate([np.zeros(12), np.ones(4)]).astype(np.int64)
    return cut_slices(xyz, component, traj)


def test_correction_flips_isolated_slices_and_fills_gaps():
    slices = _chains()
    assert len(slices) == 16
    order = np.lexsort((slices.station_index, slices.component))
    # component 0: G G O G G G O O G O O G   component 1: O G O O
    wanted = np.array([1, 1, 0, 1, 1, 1, 0, 0, 1, 0, 0, 1, 0, 1, 0, 0], dtype=np.uint8)
    labels = np.empty(16, dtype=np.uint8)
    labels[order] = wanted
    fixed = correct_labels(slices, labels)[order]
    assert fixed.dtype == np.uint8
    assert list(fixed[:12]) == [1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1]  # gaps of 1 and 2 filled
    assert list(fixed[12:]) == [0, 0, 0, 0]  # the lone guardrail slice goes
    bool_fixed = correct_labels(slices, labels.astype(bool))
    assert bool_fixed.dtype == bool


def test_correction_respects_components_and_max_gap():
    slices = _chains()
    order = np.lexsort((slices.station_index, slices.component))
    wanted = np.array([1, 1, 0, 0, 0, 1, 1, 0, 0, 0, 0, 0, 1, 1, 0, 0], dtype=np.uint8)
    labels = np.empty(16, dtype=np.uint8)
    labels[order] = wanted
    fixed = correct_labels(slices, labels)[order]
    assert list(fixed[:7]) == [1, 1, 0, 0, 0, 1, 1]  # a gap of 3 > max_gap stays
    assert list(fixed[12:]) == [1, 1, 0, 0]  # a run of two is not isolated
    fixed3 = correct_labels(slices, labels, max_gap=3)[order]
    assert list(fixed3[:7]) == [1, 1, 1, 1, 1, 1, 1]


def test_correction_keeps_confident_isolated_slices():
    """A rotating scanner breaks a rail into many components: a lone slice the classifier is
    sure of stays (`keep`); a lone unsure one still goes, and keep never makes a guardrail."""
    slices = _chains()
    order = np.lexsort((slices.station_index, slices.component))
    wanted = np.zeros(16, dtype=bool)
    wanted[[3, 13]] = True  # lone guardrail slices in both components
    labels = np.empty(16, dtype=bool)
    labels[order] = wanted
    sure = np.zeros(16, dtype=bool)
    sure[order[[3, 7]]] = True  # confident: the lone slice 3 and the "other" slice 7
    fixed = correct_labels(slices, labels, keep=sure)[order]
    assert list(np.flatnonzero(fixed)) == [3]
    assert not correct_labels(slices, labels)[order].any()


def test_scan_points_type(segmented):
    _, points, _, _, _, _ = segmented
    assert isinstance(points, ScanPoints)
    assert points.lattice is not None and points.lattice.kind == "profile"
    assert len(points.frame) == len(points.xyz) == len(points.index)
