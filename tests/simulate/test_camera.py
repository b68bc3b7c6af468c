"""Pinhole camera renders: projection matches geometry, sky, ids, depth, no halo, determinism."""

from __future__ import annotations

import numpy as np

from app.core.labels import Semantic
from app.simulate.camera import CameraConfig, render
from app.simulate.colors import COLORS, SKY_COLOR
from app.simulate.raycast import RayCaster
from tests.simulate.test_raycast import body, box_mesh, linear_motion, scene_of

# camera looking along world +x: camera x (right) = world -y, y (down) = world -z, z = world x
R_WORLD_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_pose(position=(0.0, 0.0, 1.65)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R_WORLD_CAM
    T[:3, 3] = position
    return T


def projected_bbox(lo, hi, T_world_cam: np.ndarray, cfg: CameraConfig):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array(
        [[(lo, hi)[i & 1][0], (lo, hi)[i >> 1 & 1][1], (lo, hi)[i >> 2][2]] for i in range(8)]
    )
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    cam = (corners - t) @ R  # world -> camera
    uvw = np.c_[cam, np.ones(8)] @ cfg.P.T
    uv = uvw[:, :2] / uvw[:, 2:]
    return uv.min(axis=0), uv.max(axis=0)


def mask_bbox(mask: np.ndarray):
    v, u = np.nonzero(mask)
    return np.array([u.min(), v.min()]), np.array([u.max() + 1, v.max() + 1])


def test_intrinsics():
    cfg = CameraConfig()
    np.testing.assert_allclose(cfg.K, [[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]])
    assert cfg.P.shape == (3, 4)
    np.testing.assert_array_equal(cfg.P[:, 3], 0)


def test_box_appears_where_its_corners_project():
    cfg = CameraConfig()
    lo, hi = (12.0, -1.5, 0.2), (16.0, 2.5, 2.0)  # floating box: all of it is seen
    bodies = [body("car", box_mesh(lo, hi), Semantic.CAR, instance=42)]
    caster = RayCaster(scene_of(bodies))
    T = camera_pose()
    r = render(caster, caster.scene, T, 0.0, cfg)
    assert r.rgb.shape == (375, 1242, 3) and r.rgb.dtype == np.uint8
    assert r.semantic.dtype == np.uint16 and r.instance.dtype == np.int32
    mask = r.semantic == Semantic.CAR
    (u0, v0), (u1, v1) = mask_bbox(mask)
    (pu0, pv0), (pu1, pv1) = projected_bbox(lo, hi, T, cfg)
    np.testing.assert_allclose([u0, v0, u1, v1], [pu0, pv0, pu1, pv1], atol=2.0)
    assert np.all(r.instance[mask] == 42) and np.all(r.body[mask] == 0)
    # sky wherever the box is not
    sky = ~mask
    assert np.all(r.semantic[sky] == 0) and np.all(r.instance[sky] == 0)
    assert np.all(r.body[sky] == -1) and np.all(np.isinf(r.depth[sky]))
    assert np.all(r.rgb[sky] == SKY_COLOR)
    # the front face is 12 m ahead: its depth is camera z, not ray length
    front = r.depth[mask] < 12.5
    np.testing.assert_allclose(r.depth[mask][front], 12.0, atol=1e-4)
    assert np.all(r.rgb[mask][:, 0] > r.rgb[mask][:, 2])  # red-ish car
    assert np.all(r.rgb[mask] <= COLORS[Semantic.CAR])


def test_ground_shading_fog_and_lane_marking():
    cfg = CameraConfig()
    road = body("road", box_mesh((0, -20, -0.1), (200, 20, 0.0)), Semantic.ROAD)
    lane = body("lane", box_mesh((0, -0.1, 0.0), (200, 0.1, 0.005)), Semantic.LANE_MARKING)
    caster = RayCaster(scene_of([road, lane]))
    r = render(caster, caster.scene, camera_pose(), 0.0, cfg)
    is_road, is_lane = r.semantic == Semantic.ROAD, r.semantic == Semantic.LANE_MARKING
    assert is_road.sum() > 1000 and is_lane.sum() > 100
    assert r.rgb[is_lane].mean() > 190  # white
    near, far = is_road & (r.depth < 10), is_road & (r.depth > 60)
    assert r.rgb[near].mean() > r.rgb[far].mean() + 10  # darker with distance
    assert np.all(r.semantic[: int(cfg.cy) - 5] == 0)  # above the horizon: sky


def test_moving_body_is_placed_at_render_time_and_halo_is_not_drawn():
    cfg = CameraConfig()
    lo, hi = np.array([-2.0, -0.9, 0.0]), np.array([2.0, 0.9, 1.5])
    motion = linear_motion([15.0, 0.0, 0.0], [0.0, 10.0, 0.0])
    car = body("car", box_mesh(lo, hi), Semantic.CAR, 5, motion, halo=0.4)
    caster = RayCaster(scene_of([car]), halo_probability=1.0)
    T = camera_pose((0.0, 0.0, 0.75))
    for t in (-0.3, 0.0, 0.25):
        r = render(caster, caster.scene, T, t, cfg)
        p = motion.position(t)[0]
        (u0, v0), (u1, v1) = mask_bbox(r.instance == 5)
        (pu0, pv0), (pu1, pv1) = projected_bbox(p + lo, p + hi, T, cfg)
        np.testing.assert_allclose([u0, v0, u1, v1], [pu0, pv0, pu1, pv1], atol=2.0)


def test_render_is_deterministic():
    cfg = CameraConfig(width=320, height=120, cx=160.0, cy=60.0, fx=200.0, fy=200.0)
    bodies = [
        body("road", box_mesh((0, -20, -0.1), (100, 20, 0.0)), Semantic.ROAD),
        body("car", box_mesh((10, -1, 0), (14, 1, 1.5)), Semantic.CAR, 3),
    ]
    caster = RayCaster(scene_of(bodies))
    a = render(caster, caster.scene, camera_pose(), 0.0, cfg)
    b = render(RayCaster(scene_of(bodies)), caster.scene, camera_pose(), 0.0, cfg)
    for f in ("rgb", "semantic", "instance", "body", "depth"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert a.rgb.shape == (120, 320, 3)
    assert set(np.unique(a.instance)) == {0, 3}
