"""Pinhole projection with a KITTI-like camera: hand-computed pixels, visibility, speed."""

from __future__ import annotations

import numpy as np
import pytest

from app.geometry.projection import camera_pose, pixel_indices, project
from app.geometry.transforms import make_transform

FX, CX, CY, TX = 721.5377, 609.5593, 172.854, 44.85728
P = np.array([[FX, 0.0, CX, TX], [0.0, FX, CY, 0.0], [0.0, 0.0, 1.0, 0.0]])
W, H = 1242, 375
# Velodyne (x forward, y left, z up) to camera (x right, y down, z forward).
T_CAM_VELO = make_transform(
    np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), np.zeros(3)
)


def test_hand_computed_pixels_in_camera_frame() -> None:
    xyz = np.array([[1.0, 0.5, 10.0], [0.0, 0.0, 20.0]])
    proj = project(xyz, P, np.eye(4), W, H)
    # u = (fx*x + cx*z + tx) / z, v = (fy*y + cy*z) / z
    expected = np.array(
        [
            [(FX * 1.0 + CX * 10.0 + TX) / 10.0, (FX * 0.5 + CY * 10.0) / 10.0],
            [CX + TX / 20.0, CY],
        ]
    )
    np.testing.assert_allclose(proj.uv, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(proj.uv[0], [686.198798, 208.930885], atol=1e-6)
    np.testing.assert_allclose(proj.depth, [10.0, 20.0])
    assert proj.in_image.tolist() == [True, True]


def test_sensor_to_camera_transform_is_applied() -> None:
    # The velodyne point 10 m ahead, 1 m right, 0.5 m down is camera point (1, 0.5, 10).
    proj = project(np.array([[10.0, -1.0, -0.5]]), P, T_CAM_VELO, W, H)
    np.testing.assert_allclose(proj.uv[0], [686.198798, 208.930885], atol=1e-6)
    assert proj.depth[0] == pytest.approx(10.0)


def test_points_behind_camera_are_nan_and_not_in_image() -> None:
    xyz = np.array([[0.0, 0.0, -5.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.05], [0.0, 0.0, 5.0]])
    proj = project(xyz, P, np.eye(4), W, H, min_depth=0.1)
    assert proj.in_image.tolist() == [False, False, False, True]
    assert np.all(np.isnan(proj.uv[:2]))
    assert np.all(np.isfinite(proj.uv[2:]))  # in front but closer than min_depth: finite, unseen


def test_points_outside_width_and_height_are_not_in_image() -> None:
    z = 10.0

    # Choose camera x, y so the pixels land just inside / just outside each border.
    def cam_point(u: float, v: float) -> list[float]:
        return [(u * z - CX * z - TX) / FX, (v * z - CY * z) / FX, z]

    pixels = [
        (0.001, 0.001),
        (-0.5, 10.0),
        (W - 0.01, 10.0),
        (W + 0.0, 10.0),
        (10.0, H - 0.01),
        (10.0, H),
    ]
    proj = project(np.array([cam_point(u, v) for u, v in pixels]), P, np.eye(4), W, H)
    np.testing.assert_allclose(proj.uv, pixels, atol=1e-6)
    assert proj.in_image.tolist() == [True, False, True, False, True, False]


def test_pixel_indices_look_up_a_mask() -> None:
    z = 8.0
    pixels = np.array([[100.7, 50.2], [5.3, 300.9], [2000.0, 10.0]])
    xyz = np.stack(
        [(pixels[:, 0] - CX) * z / FX - TX / FX, (pixels[:, 1] - CY) * z / FX, np.full(3, z)],
        axis=1,
    )
    proj = project(xyz, P, np.eye(4), W, H)
    rows, cols = pixel_indices(proj)
    assert rows.dtype == np.int64 and cols.dtype == np.int64
    assert rows.tolist() == [50, 300] and cols.tolist() == [100, 5]
    mask = np.zeros((H, W), dtype=bool)
    mask[300, 5] = True
    assert mask[rows, cols].tolist() == [False, True]


def test_projection_of_a_frame_sized_cloud() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.uniform([-50, -50, -3], [50, 50, 3], size=(120_000, 3))
    T = make_transform(T_CAM_VELO[:3, :3], [0.27, -0.08, -0.06])
    proj = project(xyz, P, T, W, H)
    assert proj.uv.shape == (120_000, 2)
    assert 0 < proj.in_image.sum() < 120_000
    front = proj.depth > 0.1
    assert np.isfinite(proj.uv[front]).all() and np.isnan(proj.uv[proj.depth <= 0]).all()


def test_empty_frame() -> None:
    proj = project(np.zeros((0, 3)), P, T_CAM_VELO, W, H)
    assert proj.uv.shape == (0, 2) and proj.depth.shape == (0,) and proj.in_image.shape == (0,)
    rows, cols = pixel_indices(proj)
    assert rows.shape == cols.shape == (0,)


def test_bad_shapes_are_rejected() -> None:
    with pytest.raises(ValueError, match="P must have shape"):
        project(np.zeros((3, 3)), np.eye(3), np.eye(4), W, H)
    with pytest.raises(ValueError, match="xyz must have shape"):
        project(np.zeros((3, 4)), P, np.eye(4), W, H)


def test_camera_pose_reprojects_as_the_projection_matrix() -> None:
    """The decomposed pose (centre, rotation, K) gives the pixels `project` gives, with the
    stereo baseline in P's last column and a rectifying rotation that is slightly off."""
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, 0.9999, -0.0141], [0.0, 0.0141, 0.9999]])
    T = make_transform(tilt, np.array([0.27, -0.08, -0.06])) @ T_CAM_VELO
    pose = camera_pose(P, T)
    assert np.allclose(pose.rotation.T @ pose.rotation, np.eye(3))
    # the optical centre sits TX / FX to the left of the reference camera (its baseline)
    reference = -np.linalg.solve(T[:3, :3], T[:3, 3])
    assert np.linalg.norm(pose.centre - reference) == pytest.approx(TX / FX, rel=1e-2)
    rng = np.random.default_rng(0)
    xyz = np.column_stack(
        [rng.uniform(5, 60, 500), rng.uniform(-20, 20, 500), rng.normal(0, 1, 500)]
    )
    proj = project(xyz, P, T, W, H)
    cam = (xyz - pose.centre) @ pose.rotation
    uvw = cam @ pose.K.T
    np.testing.assert_allclose(uvw[:, :2] / uvw[:, 2:], proj.uv, atol=0.05)
    with pytest.raises(ValueError, match="singular"):
        camera_pose(np.zeros((3, 4)), T)
