"""Small synthetic KITTI folders written on the fly, for bad-input tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

IDENTITY_3X4 = "1 0 0 0 0 1 0 0 0 0 1 0"
P_LINE = "721.5377 0 609.5593 44.85728 0 721.5377 172.854 0.2163791 0 0 1 0.002745884"


def write_scan(path: Path, n: int = 100, seed: int = 0) -> np.ndarray:
    path.parent.mkdir(parents=True, exist_ok=True)
    pts = np.random.default_rng(seed).uniform(-20, 20, (n, 4)).astype(np.float32)
    pts.tofile(path)
    return pts


def make_semantickitti(root: Path, frames: int = 3, poses: int | None = None) -> Path:
    """A minimal SemanticKITTI sequence: scans, calib.txt, poses.txt, times.txt, labels."""
    root.mkdir(parents=True, exist_ok=True)
    for i in range(frames):
        pts = write_scan(root / "velodyne" / f"{i:06d}.bin", seed=i)
        (root / "labels").mkdir(exist_ok=True)
        np.full(len(pts), (7 << 16) | 40, dtype=np.uint32).tofile(
            root / "labels" / f"{i:06d}.label"
        )
    calib = [f"P{k}: {P_LINE}" for k in range(4)] + [f"Tr: {IDENTITY_3X4}"]
    (root / "calib.txt").write_text("\n".join(calib) + "\n")
    n_poses = frames if poses is None else poses
    rows = [f"1 0 0 {i * 1.0} 0 1 0 0 0 0 1 0" for i in range(n_poses)]
    (root / "poses.txt").write_text("\n".join(rows) + "\n")
    (root / "times.txt").write_text("\n".join(f"{i * 0.1:.6e}" for i in range(frames)) + "\n")
    return root


def make_kitti_raw(root: Path, frames: int = 3, oxts: int | None = None) -> Path:
    """A minimal KITTI raw date folder with one sync drive and OXTS packets."""
    date = root / "2011_09_26"
    sync = date / "2011_09_26_drive_0001_sync"
    for i in range(frames):
        write_scan(sync / "velodyne_points" / "data" / f"{i:010d}.bin", seed=i)
    (date / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\n"
        "S_rect_02: 1.242000e+03 3.750000e+02\n"
        "R_rect_00: 1 0 0 0 1 0 0 0 1\n"
        f"P_rect_02: {P_LINE}\n"
    )
    rigid = "R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n"
    (date / "calib_velo_to_cam.txt").write_text(rigid)
    (date / "calib_imu_to_velo.txt").write_text(rigid)
    n_oxts = frames if oxts is None else oxts
    oxts_dir = sync / "oxts" / "data"
    oxts_dir.mkdir(parents=True)
    for i in range(n_oxts):
        packet = [49.0, 8.4 + i * 1e-5, 110.0, 0.0, 0.0, 0.3] + [0.0] * 24
        (oxts_dir / f"{i:010d}.txt").write_text(" ".join(f"{v:.10f}" for v in packet))
    stamps = [f"2011-09-26 13:02:2{i}.103794725" for i in range(frames)]
    (sync / "velodyne_points" / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    return sync
