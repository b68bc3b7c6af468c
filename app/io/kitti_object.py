"""KITTI object-benchmark frames: calibration and `label_2` 3D boxes.

Not a survey format (single frames, no poses); used to check projection and point-in-box logic
against annotated objects, and later as image/box fixtures for the clutter pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.geometry.transforms import rot_y
from app.io.kitti_calib import matrix_3x4, read_calib_file, rectifying_4x4, rigid_4x4
from app.io.survey import Camera


@dataclass(frozen=True)
class ObjectBox:
    """One `label_2` line. Box in the rectified camera frame (x right, y down, z forward)."""

    type: str
    truncated: float
    occluded: int
    alpha: float
    bbox: np.ndarray  # (4,) left, top, right, bottom pixels
    dimensions: np.ndarray  # (3,) height, width, length metres
    location: np.ndarray  # (3,) bottom centre
    rotation_y: float

    def contains(self, xyz_cam: np.ndarray) -> np.ndarray:
        """(N,) bool: which rectified-camera points lie inside the 3D box."""
        local = (xyz_cam - self.location) @ rot_y(self.rotation_y)  # rows: R^T (p - loc)
        h, w, length = self.dimensions
        return (
            (np.abs(local[:, 0]) <= length / 2)
            & (local[:, 1] <= 0)
            & (local[:, 1] >= -h)
            & (np.abs(local[:, 2]) <= w / 2)
        )


def read_object_labels(path: Path) -> list[ObjectBox]:
    """All labelled objects of a frame, DontCare regions excluded."""
    if not path.is_file():
        raise InputError(path, "label file is missing")
    boxes = []
    for line_no, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (15, 16):
            raise InputError(path, f"line {line_no} has {len(fields)} fields, expected 15")
        if fields[0] == "DontCare":
            continue
        v = np.array(fields[1:15], dtype=np.float64)
        boxes.append(ObjectBox(fields[0], v[0], int(v[1]), v[2], v[3:7], v[7:10], v[10:13], v[13]))
    return boxes


def read_object_camera(path: Path, width: int, height: int) -> Camera:
    """Camera `image_2` of an object-benchmark calib file: P2 @ R0_rect @ Tr_velo_to_cam."""
    entries = read_calib_file(path)
    P2 = matrix_3x4(entries, "P2", path)
    T = rectifying_4x4(entries, "R0_rect", path) @ rigid_4x4(entries, "Tr_velo_to_cam", path)
    return Camera("image_2", P2, T, width, height, "P2")


def rectified_camera_points(camera: Camera, xyz: np.ndarray) -> np.ndarray:
    """Velodyne points in the rectified camera-0 frame, where label_2 boxes live."""
    T = camera.T_cam_sensor
    return xyz @ T[:3, :3].T + T[:3, 3]
