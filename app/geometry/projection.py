"""Pinhole projection of LiDAR points into a camera image (clutter pipeline: points under masks).

For KITTI pass `P = P_rect_02` and `T_cam_sensor = R0_rect (as 4x4) @ Tr_velo_to_cam`; the two are
folded into one 3x4 matrix so a frame costs a single float64 matmul.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.geometry._arrays import as_matrix, as_points


@dataclass
class Projection:
    """Where each point lands: pixels (nan behind the camera), depth, and whether it is seen."""

    uv: np.ndarray  # (N, 2) float64 pixel coordinates (u = column, v = row)
    depth: np.ndarray  # (N,) float64, the homogeneous w (camera z for a rectified P)
    in_image: np.ndarray  # (N,) bool: depth > min_depth and inside [0, width) x [0, height)


def projection_matrix(P: np.ndarray, T_cam_sensor: np.ndarray) -> np.ndarray:
    """The 3x4 matrix P @ T_cam_sensor taking sensor points straight to homogeneous pixels."""
    return as_matrix(P, (3, 4), "P") @ as_matrix(T_cam_sensor, (4, 4), "T_cam_sensor")


def project(
    xyz: np.ndarray,
    P: np.ndarray,
    T_cam_sensor: np.ndarray,
    width: int,
    height: int,
    min_depth: float = 0.1,
) -> Projection:
    """Project sensor-frame points (N, 3) with [u*w, v*w, w] = P @ T_cam_sensor @ [x, y, z, 1]."""
    xyz = as_points(xyz)
    M = projection_matrix(P, T_cam_sensor)
    # One (N, 3) buffer holds [u, v, w]; uv and depth are views of it (fewer fresh pages per frame).
    uvw = xyz @ M[:, :3].T
    uvw += M[:, 3]
    depth = uvw[:, 2]
    # Behind the camera the division would mirror points into the image; mark them nan instead.
    inv_w = np.full(len(depth), np.nan)
    np.divide(1.0, depth, out=inv_w, where=depth > 0.0)
    uv = uvw[:, :2]
    uv *= inv_w[:, None]
    u, v = uv[:, 0], uv[:, 1]
    with np.errstate(invalid="ignore"):
        in_image = depth > min_depth
        in_image &= u >= 0.0
        in_image &= u < width
        in_image &= v >= 0.0
        in_image &= v < height
    return Projection(uv=uv, depth=depth, in_image=in_image)


def pixel_indices(proj: Projection) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) int64 of the in-image points, in point order, to index masks `m[rows, cols]`."""
    uv = proj.uv[proj.in_image]
    rows = np.floor(uv[:, 1]).astype(np.int64)
    cols = np.floor(uv[:, 0]).astype(np.int64)
    return rows, cols


@dataclass(frozen=True)
class CameraPose:
    """Where a camera sits in its scanner's frame and how it images: enough to place its image
    in a 3D scene so that every pixel lies on the ray it sees (clutter review draws boxes on it).
    """

    rotation: np.ndarray  # (3, 3) camera -> sensor (OpenCV axes: +X right, +Y down, +Z forward)
    centre: np.ndarray  # (3,) the optical centre in sensor coordinates
    K: np.ndarray  # (3, 3) intrinsics

    def pixel_ray(self, u: float, v: float) -> np.ndarray:
        """(3,) the direction, in camera coordinates at unit depth, that pixel (u, v) sees."""
        return np.linalg.solve(self.K, np.array([u, v, 1.0]))


def camera_pose(P: np.ndarray, T_cam_sensor: np.ndarray) -> CameraPose:
    """Decompose `P @ T_cam_sensor` (P = K [I | t], rectified; T: sensor -> rectified reference)
    into the camera's pose in the sensor frame and K. KITTI's rectifying rotation folded into T
    is not exactly orthonormal in float, so the rotation is its nearest orthonormal matrix."""
    P = as_matrix(P, (3, 4), "P")
    T = as_matrix(T_cam_sensor, (4, 4), "T_cam_sensor")
    K = P[:, :3]
    if abs(np.linalg.det(K)) < 1e-9:
        raise ValueError("P: its left 3x3 (the intrinsics) is singular")
    t_cam = T[:3, 3] + np.linalg.solve(K, P[:, 3])  # camera coordinates of the sensor origin
    u, _, vt = np.linalg.svd(T[:3, :3])
    R_cam_sensor = u @ vt
    rotation = R_cam_sensor.T
    return CameraPose(rotation=rotation, centre=-rotation @ t_cam, K=K.copy())
