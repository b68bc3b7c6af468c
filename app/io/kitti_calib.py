"""KITTI calibration text files: `KEY: v1 v2 ...` lines.

Used by the raw-drive (`calib_cam_to_cam.txt`, `calib_velo_to_cam.txt`, `calib_imu_to_velo.txt`),
odometry/SemanticKITTI (`calib.txt`) and object-benchmark (`calib/NNNNNN.txt`) readers. Every
shape problem is reported with the file and key that has it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.geometry.transforms import make_transform


def read_calib_file(path: Path) -> dict[str, np.ndarray]:
    """All numeric entries of a KITTI calibration file; text entries (calib_time) are skipped."""
    if not path.is_file():
        raise InputError(path, "calibration file is missing")
    entries: dict[str, np.ndarray] = {}
    for line_no, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise InputError(path, f"line {line_no} is not 'KEY: values'")
        try:
            entries[key.strip()] = np.array(value.split(), dtype=np.float64)
        except ValueError:
            continue  # e.g. "calib_time: 09-Jan-2012 13:57:47"
    return entries


def require(entries: dict[str, np.ndarray], key: str, count: int, path: Path) -> np.ndarray:
    """The values of KEY, which must be exactly COUNT finite numbers."""
    if key not in entries:
        raise InputError(path, f"calibration entry {key} is missing")
    values = entries[key]
    if values.size != count:
        raise InputError(
            path, f"calibration entry {key} has {values.size} values, expected {count}"
        )
    if not np.isfinite(values).all():
        raise InputError(path, f"calibration entry {key} has NaN or infinite values")
    return values


def matrix_3x4(entries: dict[str, np.ndarray], key: str, path: Path) -> np.ndarray:
    return require(entries, key, 12, path).reshape(3, 4)


def rigid_4x4(entries: dict[str, np.ndarray], key: str, path: Path) -> np.ndarray:
    """A 3x4 [R|t] entry (12 values) as a 4x4 transform."""
    m = matrix_3x4(entries, key, path)
    return make_transform(m[:, :3], m[:, 3])


def rigid_from_r_t(path: Path) -> np.ndarray:
    """Raw-drive rigid calibration (`R:` 9 values, `T:` 3 values) as a 4x4 transform."""
    entries = read_calib_file(path)
    R = require(entries, "R", 9, path).reshape(3, 3)
    t = require(entries, "T", 3, path)
    return make_transform(R, t)


def rectifying_4x4(entries: dict[str, np.ndarray], key: str, path: Path) -> np.ndarray:
    """A 3x3 rectifying rotation entry (R_rect_00, R0_rect) as a 4x4 transform."""
    R = require(entries, key, 9, path).reshape(3, 3)
    return make_transform(R, np.zeros(3))
