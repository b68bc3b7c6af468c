"""Rigid transforms as 4x4 homogeneous float64 matrices (sensor -> world, sensor -> camera).

Poses chain left to right (`compose(T_world_imu, T_imu_velo)` maps velodyne points to the world),
and inverses use R^T so they stay exactly rigid over long drives.
"""

from __future__ import annotations

import numpy as np

from app.geometry._arrays import as_matrix, as_points


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build the 4x4 matrix mapping x to R @ x + t."""
    R = as_matrix(R, (3, 3), "R")
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if t.shape != (3,):
        raise ValueError(f"t must have 3 values, got {t.size}")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform via R^T (exact and cheaper than np.linalg.inv)."""
    T = as_matrix(T, (4, 4), "T")
    R_t = T[:3, :3].T
    out = np.eye(4)
    out[:3, :3] = R_t
    out[:3, 3] = -R_t @ T[:3, 3]
    return out


def apply(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Map points (N, 3) through T; float64 result so world coordinates keep their precision."""
    T = as_matrix(T, (4, 4), "T")
    xyz = as_points(xyz)
    return xyz @ T[:3, :3].T + T[:3, 3]


def compose(*Ts: np.ndarray) -> np.ndarray:
    """Matrix product T1 @ T2 @ ... (left to right); identity when called with nothing."""
    out = np.eye(4)
    for i, T in enumerate(Ts):
        out = out @ as_matrix(T, (4, 4), f"transform {i}")
    return out


def rot_x(a: float) -> np.ndarray:
    """Rotation by `a` radians about the x axis."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by `a` radians about the y axis."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation by `a` radians about the z axis."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll): the KITTI OXTS attitude convention."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def from_3x4(values: np.ndarray | list[float]) -> np.ndarray:
    """4x4 from the 12 numbers of a [R | t] row-major 3x4 (KITTI calib and poses files)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != 12:
        raise ValueError(f"a 3x4 transform needs 12 values, got {arr.size} (shape {arr.shape})")
    T = np.eye(4)
    T[:3, :] = arr.reshape(3, 4)
    return T


def is_rigid(T: np.ndarray, atol: float = 1e-6) -> bool:
    """True when T is a proper rigid transform: orthonormal R, det +1, bottom row 0 0 0 1."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=atol)
        and np.allclose(R.T @ R, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) <= atol
    )


def rotation_angle(R: np.ndarray) -> float:
    """Angle (radians, 0..pi) of the rotation R, e.g. to measure how far two poses disagree."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (4, 4):
        R = R[:3, :3]
    R = as_matrix(R, (3, 3), "R")
    # atan2 of (sin, cos) stays accurate for tiny angles, where arccos of the trace loses digits.
    skew = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.arctan2(np.linalg.norm(skew) / 2.0, (np.trace(R) - 1.0) / 2.0))


def relative(Ta: np.ndarray, Tb: np.ndarray) -> np.ndarray:
    """invert(Ta) @ Tb: pose b expressed in the frame of pose a."""
    return invert(Ta) @ as_matrix(Tb, (4, 4), "Tb")
