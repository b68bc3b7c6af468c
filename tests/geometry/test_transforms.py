"""Rigid transforms: inverses, composition order, KITTI conventions, validation."""

from __future__ import annotations

import numpy as np
import pytest

from app.geometry.transforms import (
    apply,
    compose,
    euler_to_matrix,
    from_3x4,
    invert,
    is_rigid,
    make_transform,
    relative,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle,
)


def _pose(roll: float, pitch: float, yaw: float, t: tuple[float, float, float]) -> np.ndarray:
    return make_transform(euler_to_matrix(roll, pitch, yaw), np.array(t))


def test_make_transform_layout() -> None:
    T = make_transform(rot_z(0.3), [1.0, 2.0, 3.0])
    assert T.dtype == np.float64
    np.testing.assert_allclose(T[:3, :3], rot_z(0.3))
    np.testing.assert_allclose(T[:3, 3], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


def test_invert_gives_identity_both_ways() -> None:
    T = _pose(0.1, -0.2, 2.5, (456_789.12, 5_432_100.5, 112.3))
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(T @ invert(T), np.eye(4), atol=1e-7)
    assert is_rigid(invert(T))


def test_apply_rotates_then_translates() -> None:
    T = make_transform(rot_z(np.pi / 2), [10.0, 0.0, 0.0])
    out = apply(T, np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 5.0]]))
    np.testing.assert_allclose(out, [[10.0, 1.0, 0.0], [8.0, 0.0, 5.0]], atol=1e-12)
    assert out.dtype == np.float64


def test_apply_keeps_float64_precision_for_float32_input() -> None:
    T = make_transform(np.eye(3), [500_000.0, 5_000_000.0, 0.0])
    out = apply(T, np.array([[0.001, 0.002, 0.0]], dtype=np.float32))
    assert out.dtype == np.float64
    assert abs(out[0, 0] - 500_000.001) < 1e-6


def test_compose_is_left_to_right() -> None:
    A = make_transform(rot_z(np.pi / 2), [0.0, 0.0, 0.0])
    B = make_transform(np.eye(3), [1.0, 0.0, 0.0])
    p = np.array([[0.0, 0.0, 0.0]])
    # compose(A, B) applies B first, then A: the translated point is rotated onto +y.
    np.testing.assert_allclose(apply(compose(A, B), p), [[0.0, 1.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(compose(A, B), A @ B)
    np.testing.assert_allclose(compose(), np.eye(4))


def test_euler_matches_elementary_rotations() -> None:
    roll, pitch, yaw = 0.05, -0.1, 1.2
    R = euler_to_matrix(roll, pitch, yaw)
    np.testing.assert_allclose(R, rot_z(yaw) @ rot_y(pitch) @ rot_x(roll))
    assert is_rigid(make_transform(R, np.zeros(3)))
    # Pure yaw turns the x axis (forward) counter-clockwise.
    np.testing.assert_allclose(
        euler_to_matrix(0.0, 0.0, np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-12
    )


def test_elementary_rotations_are_right_handed() -> None:
    np.testing.assert_allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_from_3x4_accepts_flat_and_matrix() -> None:
    values = [1, 0, 0, 1.5, 0, 1, 0, -2.0, 0, 0, 1, 0.25]
    T = from_3x4(values)
    np.testing.assert_allclose(T[:3, 3], [1.5, -2.0, 0.25])
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(from_3x4(np.array(values).reshape(3, 4)), T)


@pytest.mark.parametrize("n", [11, 13, 16])
def test_from_3x4_rejects_wrong_count(n: int) -> None:
    with pytest.raises(ValueError, match=f"12 values, got {n}"):
        from_3x4(list(range(n)))


def test_is_rigid_rejects_scale_reflection_and_bad_bottom_row() -> None:
    assert is_rigid(_pose(0.3, 0.2, 0.1, (1, 2, 3)))
    assert not is_rigid(make_transform(2.0 * np.eye(3), np.zeros(3)))
    assert not is_rigid(make_transform(np.diag([1.0, 1.0, -1.0]), np.zeros(3)))
    bad = np.eye(4)
    bad[3, 0] = 0.5
    assert not is_rigid(bad)
    assert not is_rigid(np.eye(3))


def test_rotation_angle_small_and_large() -> None:
    assert rotation_angle(np.eye(3)) == 0.0
    assert rotation_angle(rot_x(1e-7)) == pytest.approx(1e-7, rel=1e-6)
    assert rotation_angle(rot_y(2.0)) == pytest.approx(2.0)
    assert rotation_angle(rot_z(np.pi)) == pytest.approx(np.pi)
    assert rotation_angle(_pose(0.0, 0.0, -0.4, (5, 5, 5))) == pytest.approx(0.4)


def test_relative_pose() -> None:
    Ta = _pose(0.01, 0.02, 0.5, (100.0, 200.0, 3.0))
    Tb = _pose(0.01, 0.02, 0.7, (101.0, 201.0, 3.1))
    D = relative(Ta, Tb)
    np.testing.assert_allclose(Ta @ D, Tb, atol=1e-9)
    assert rotation_angle(D) == pytest.approx(0.2, abs=1e-9)
