"""LiDAR odometry with KISS-ICP for drives that have no GNSS/INS poses.

Poses are cached under the data directory, keyed by the scan files' names, sizes and times, so
`mmsclean info` and every pipeline run after the first reuse them. They are marked as estimated
on the Survey.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from app.core.settings import get_settings
from app.io.point_files import write_atomically
from app.io.velodyne_bin import read_velodyne_bin, sweep_fraction

log = logging.getLogger(__name__)

ODOMETRY_VERSION = "kiss-icp-1"  # bump when the way poses are computed changes


def _cache_key(scan_files: Sequence[Path]) -> str:
    h = hashlib.sha256(ODOMETRY_VERSION.encode())
    for f in scan_files:
        st = f.stat()
        h.update(f"{f.resolve()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:32]


def kiss_icp_poses(scan_files: Sequence[Path], kitti_correction: bool = True) -> np.ndarray:
    """(N, 4, 4) sensor -> world poses, world = the first scan's sensor frame."""
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP
    from kiss_icp.pybind import kiss_icp_pybind

    config = load_config(None)
    odometry = KissICP(config)
    poses = np.empty((len(scan_files), 4, 4))
    for i, path in enumerate(scan_files):
        xyz = read_velodyne_bin(path).xyz
        if kitti_correction:  # the HDL-64E intrinsic fix KISS-ICP applies to KITTI scans
            xyz = np.asarray(
                kiss_icp_pybind._correct_kitti_scan(kiss_icp_pybind._Vector3dVector(xyz))
            )
        odometry.register_frame(xyz, sweep_fraction(xyz))
        poses[i] = odometry.last_pose
    return poses


def estimated_poses(scan_files: Sequence[Path]) -> np.ndarray:
    """KISS-ICP poses of the scans, from the cache when the same files were seen before."""
    cache = get_settings().cache_dir / "odometry" / f"{_cache_key(scan_files)}.npy"
    if cache.is_file():
        poses = np.load(cache)
        if poses.shape == (len(scan_files), 4, 4):
            return poses
    log.info("estimating poses of %d scans with KISS-ICP", len(scan_files))
    poses = kiss_icp_poses(scan_files)
    write_atomically(cache, lambda fh: np.save(fh, poses))
    return poses
