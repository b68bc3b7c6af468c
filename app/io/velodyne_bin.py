"""KITTI Velodyne `.bin` scans: float32 x, y, z, reflectance per point, 16 bytes a point."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.io.survey import PointCloud

BYTES_PER_POINT = 16


def bin_point_count(path: Path) -> int:
    """Points in a scan from its size; a size not a multiple of 16 means a truncated file."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InputError(path, "scan file does not exist") from None
    if size % BYTES_PER_POINT:
        raise InputError(
            path,
            f"truncated: {size} bytes is not a multiple of {BYTES_PER_POINT} "
            "(float32 x, y, z, reflectance per point)",
        )
    return size // BYTES_PER_POINT


def check_finite(path: Path, xyz: np.ndarray) -> None:
    """Refuse NaN/inf coordinates: they poison every neighbour search downstream."""
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputError(path, f"has {int(bad.sum())} points with NaN or infinite coordinates")


def sweep_fraction(xyz: np.ndarray) -> np.ndarray:
    """Where in its sweep (0..1) a rotating HDL-64E measured each point, from its azimuth.

    The head turns clockwise seen from above; KITTI's sweep starts and ends facing backwards and
    is half done facing forwards, when the cameras are triggered.
    """
    return 0.5 * (-np.arctan2(xyz[:, 1], xyz[:, 0]) / np.pi + 1.0)


def read_velodyne_bin(
    path: Path, sweep_start: float | None = None, sweep_end: float | None = None
) -> PointCloud:
    """A scan in file order; with the sweep's start and end times, per-point times too."""
    bin_point_count(path)
    raw = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    check_finite(path, raw[:, :3])
    xyz = raw[:, :3].astype(np.float64)
    time = None
    if sweep_start is not None and sweep_end is not None:
        time = sweep_start + sweep_fraction(xyz) * (sweep_end - sweep_start)
    return PointCloud(xyz=xyz, intensity=raw[:, 3].copy(), time=time)
