"""Scanner patterns (HDL-64E, profile scanner) and simulated scans: ranges, noise, phantoms."""

from __future__ import annotations

import numpy as np

from app.core.labels import Semantic
from app.io.velodyne_bin import sweep_fraction
from app.simulate.raycast import RayCaster
from app.simulate.scanners import (
    HDL64Config,
    ProfileConfig,
    hdl64_pattern,
    profile_pattern,
    scan,
)
from app.simulate.scene import Motion
from tests.simulate.test_raycast import body, box_distance, box_mesh, plane_mesh, scene_of

EXACT = {"range_noise_m": 0.0, "dropout": 0.0}


def still(x: float = 0.0, y: float = 0.0) -> Motion:
    return Motion(np.array([-100.0, 100.0]), np.array([[x, y, 0.0], [x, y, 0.0]]), np.zeros(2))


def driving(speed: float, y: float = 0.0) -> Motion:
    t = np.array([-100.0, 100.0])
    return Motion(t, np.stack([speed * t, np.full(2, y), np.zeros(2)], 1), np.zeros(2))


def ground_caster(**kw) -> RayCaster:
    return RayCaster(scene_of([body("road", plane_mesh(-1000, 1000, -300, 300))]), **kw)


def test_hdl64_pattern_geometry_and_timing():
    cfg = HDL64Config()
    p = hdl64_pattern(cfg, sweep_start=12.5)
    assert len(p) == 64 * 4000 == cfg.beams * cfg.columns
    np.testing.assert_allclose(np.linalg.norm(p.directions, axis=1), 1.0)
    elevation = np.degrees(np.arcsin(p.directions[:, 2]))
    np.testing.assert_allclose([elevation.max(), elevation.min()], [2.0, -24.8])
    np.testing.assert_allclose(elevation[p.ring == 0], 2.0)
    assert len(np.unique(np.round(elevation, 9))) == 64
    frac = sweep_fraction(p.directions)
    np.testing.assert_allclose(frac, (p.times - 12.5) * cfg.rate_hz, atol=1e-9)
    assert p.times.min() == 12.5 and p.times.max() < 12.6
    np.testing.assert_allclose(p.times.max(), 12.6 - 0.1 / 4000)
    assert np.all(np.diff(p.times) >= 0)
    # backwards at the start, forwards half way
    np.testing.assert_allclose(
        p.directions[p.column == 0, 0] / np.cos(np.radians(elevation[:64])), -1
    )
    np.testing.assert_allclose(
        p.directions[p.column == 2000, 0] / np.cos(np.radians(elevation[:64])), 1
    )
    assert p.ring.dtype == np.uint8 and p.column.dtype == np.int32 and p.step.dtype == np.int32
    assert set(np.unique(p.column)) == set(range(4000))


def test_profile_pattern_planes_and_rates():
    cfg = ProfileConfig()
    p = profile_pattern(cfg, 1.0, 1.05)
    assert cfg.points_per_profile == 3000
    assert len(p) == 5 * 3000
    np.testing.assert_array_equal(np.unique(p.column), [100, 101, 102, 103, 104])
    np.testing.assert_allclose(p.directions[:, 0], 0.0)  # the sensor's y-z plane
    np.testing.assert_allclose(np.linalg.norm(p.directions, axis=1), 1.0)
    starts = p.times[p.step == 0]
    np.testing.assert_allclose(starts, [1.0, 1.01, 1.02, 1.03, 1.04])
    np.testing.assert_allclose(np.diff(p.times[p.column == 101]), 1 / 300_000)
    angles = np.degrees(np.arctan2(p.directions[:3000, 1], -p.directions[:3000, 2]))
    np.testing.assert_allclose(np.diff(np.unwrap(np.radians(angles))), np.radians(0.12))
    assert np.all(np.diff(p.times) > 0)
    assert len(profile_pattern(cfg, 0.0, 1.0)) == 100 * 3000
    np.testing.assert_array_equal(p.step[:3000], np.arange(3000))


def test_hdl64_on_flat_ground_gives_exact_ranges():
    cfg = HDL64Config(**EXACT)
    caster = ground_caster()
    pts = scan(
        caster,
        hdl64_pattern(cfg, 0.0),
        still(5, 3),
        cfg.T_vehicle_sensor,
        cfg,
        np.random.default_rng(0),
    )
    elevation = np.radians(np.linspace(2.0, -24.8, 64))
    expected = 1.73 / np.sin(-elevation)
    seen = (expected >= cfg.min_range) & (expected <= cfg.max_range)
    assert len(pts) == seen.sum() * 4000  # every downward ray returns
    np.testing.assert_allclose(pts.range, expected[pts.ring], rtol=1e-6)
    np.testing.assert_allclose(pts.xyz_world[:, 2], 0.0, atol=1e-5)
    sensor = np.array([5.0, 3.0, 1.73])
    np.testing.assert_allclose(np.linalg.norm(pts.xyz_world - sensor, axis=1), pts.range)
    assert np.all(pts.body == 0) and not pts.halo.any()
    assert pts.intensity.dtype == np.float32
    assert pts.intensity.min() >= 0.0 and pts.intensity.max() <= 1.0


def test_driving_sensor_places_each_ray_at_its_own_pose():
    cfg = ProfileConfig(**EXACT)
    caster = ground_caster()
    motion = driving(20.0)
    pts = scan(
        caster,
        profile_pattern(cfg, 0.0, 0.2),
        motion,
        cfg.T_vehicle_sensor,
        cfg,
        np.random.default_rng(0),
    )
    np.testing.assert_allclose(pts.xyz_world[:, 2], 0.0, atol=1e-5)
    # each profile lies in the plane x = sensor x at each point's own time (no tilt)
    np.testing.assert_allclose(pts.xyz_world[:, 0], 20.0 * pts.time - 1.0, atol=1e-6)
    assert np.ptp(pts.xyz_world[pts.column == 5, 0]) > 0.05  # 10 ms x 20 m/s within a profile


def test_noise_dropout_and_intensity_statistics():
    cfg = HDL64Config()
    rng = np.random.default_rng(5)
    bodies = [
        body("road", plane_mesh(-200, 200, -200, 200), refl=0.2),
        body("sign", box_mesh((8, -3, 0), (8.2, 3, 5)), Semantic.TRAFFIC_SIGN, 1, refl=0.9),
    ]
    caster = RayCaster(scene_of(bodies))
    pts = scan(caster, hdl64_pattern(cfg, 0.0), still(), cfg.T_vehicle_sensor, cfg, rng)
    exact = scan(
        caster, hdl64_pattern(cfg, 0.0), still(), cfg.T_vehicle_sensor, HDL64Config(**EXACT), rng
    )
    kept = len(pts) / len(exact)
    assert 0.94 < kept < 0.96
    road = pts.body == 0
    residual = (
        pts.range[road] - 1.73 / np.sin(-np.radians(np.linspace(2, -24.8, 64)))[pts.ring[road]]
    )
    assert abs(residual.std() - 0.02) < 0.001 and abs(residual.mean()) < 0.001
    assert pts.intensity[pts.body == 1].mean() > 2 * pts.intensity[road].mean()


def test_scan_is_deterministic():
    cfg = HDL64Config()
    caster = ground_caster()
    a = scan(
        caster,
        hdl64_pattern(cfg, 0.0),
        still(),
        cfg.T_vehicle_sensor,
        cfg,
        np.random.default_rng(11),
    )
    b = scan(
        caster,
        hdl64_pattern(cfg, 0.0),
        still(),
        cfg.T_vehicle_sensor,
        cfg,
        np.random.default_rng(11),
    )
    for f in ("xyz_world", "time", "intensity", "ring", "column", "body", "range"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def points_in_body_frame(motion: Motion, xyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    Rt, tl = motion.world_to_local(t)
    return np.einsum("nij,nj->ni", Rt, xyz) + tl


def test_box_crossing_hdl64_sweep_is_smeared():
    """A car crossing the sweep at 15 m/s in the direction the beam turns: its points spread over
    more than its length, by the distance it drove while the beam was on it, and each point lies
    on the car where it was at that point's own time."""
    cfg = HDL64Config(**EXACT)
    lo, hi = np.array([-2.25, -0.9, 0.0]), np.array([2.25, 0.9, 1.5])
    speed = 15.0
    # at t = 0.05 s the beam faces forward and turns towards -y; the car drives along -y
    start, end = [6.0, speed * 1.05, 0.0], [6.0, -speed * 0.95, 0.0]
    car_path = Motion(np.array([-1.0, 1.0]), np.array([start, end]), np.full(2, -np.pi / 2))
    bodies = [
        body("road", plane_mesh(-100, 100, -100, 100)),
        body("car", box_mesh(lo, hi), Semantic.CAR, 1, car_path),
    ]
    caster = RayCaster(scene_of(bodies))
    pts = scan(
        caster,
        hdl64_pattern(cfg, 0.0),
        still(),
        cfg.T_vehicle_sensor,
        cfg,
        np.random.default_rng(0),
    )
    car = pts.body == 1
    assert car.sum() > 500
    extent = np.ptp(pts.xyz_world[car, 1])
    length = hi[0] - lo[0]
    on_car = np.ptp(pts.time[car])
    assert extent > length + 0.5 * speed * on_car
    assert abs(extent - (length + speed * on_car)) < 0.15
    local = points_in_body_frame(car_path, pts.xyz_world[car], pts.time[car])
    assert np.abs(box_distance(local, lo, hi)).max() < 1e-3
    # the same points do not fit the car at one single time
    frozen = points_in_body_frame(car_path, pts.xyz_world[car], np.full(car.sum(), 0.05))
    assert np.abs(box_distance(frozen, lo, hi)).max() > 0.1


def test_profile_scanner_turns_overtaking_car_into_long_phantom():
    """Survey vehicle at 10 m/s, car overtaking at 15 m/s in the next lane: the scan plane moves
    over the car at 5 m/s relative speed, for length / 5 s, while it advances 10 m/s in the map:
    the 4.5 m car becomes a 9 m phantom."""
    cfg = ProfileConfig(**EXACT)
    lo, hi = np.array([-2.25, -0.9, 0.0]), np.array([2.25, 0.9, 1.5])
    car_path = driving(15.0, y=3.5)
    # scan plane at x = 10 t - 1, car centre at 15 t - 21: they meet at t = 4 s
    car_path = Motion(car_path.times, car_path.positions - [21.0, 0, 0], car_path.yaws)
    bodies = [
        body("road", plane_mesh(-200, 400, -50, 50)),
        body("car", box_mesh(lo, hi), Semantic.CAR, 2, car_path),
    ]
    caster = RayCaster(scene_of(bodies))
    pts = scan(
        caster,
        profile_pattern(cfg, 0.0, 8.0),
        driving(10.0),
        cfg.T_vehicle_sensor,
        cfg,
        np.random.default_rng(0),
    )
    car = pts.body == 1
    assert car.sum() > 1000
    extent = np.ptp(pts.xyz_world[car, 0])
    length = hi[0] - lo[0]
    np.testing.assert_allclose(extent, length * 10.0 / 5.0, rtol=0.03)
    local = points_in_body_frame(car_path, pts.xyz_world[car], pts.time[car])
    assert np.abs(box_distance(local, lo, hi)).max() < 1e-3


def test_sensor_rotation_matches_motion_rotations():
    from app.simulate.scanners import _rotate

    rng = np.random.default_rng(2)
    t = np.linspace(0, 9, 50)
    motion = Motion(t, rng.normal(size=(50, 3)), rng.uniform(-7, 7, 50), rng.uniform(-0.2, 0.2, 50))
    q = rng.uniform(0, 9, 1000)
    v = rng.normal(size=(1000, 3))
    yaw, pitch = motion.yaw(q), motion.pitch(q)
    got = _rotate((np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)), v)
    np.testing.assert_allclose(got, np.einsum("nij,nj->ni", motion.rotations(q), v), atol=1e-12)
