"""Reader for KITTI raw "sync" drives (format `kitti-raw`).

Layout (as unpacked from the KITTI downloads):

    <date>/calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt
    <date>/<date>_drive_NNNN_sync/velodyne_points/data/NNNNNNNNNN.bin (+ timestamps*.txt)
                                  (or NNNNNNNNNN.laz: compressed scans with per-point time)
                                  image_02/data/NNNNNNNNNN.png
                                  oxts/data/NNNNNNNNNN.txt (+ timestamps.txt)

SOURCE is the sync folder, or a folder holding exactly one. The calibration files are searched in
the sync folder, its parents and their `<date>_calib/<date>` siblings. Poses: OXTS packets through
the devkit's Mercator convention; a drive without oxts gets KISS-ICP odometry poses, marked as
estimated. With `timestamps_start.txt` / `timestamps_end.txt` every point gets its time from
its azimuth within the sweep. Camera: image_02 (left colour),
`P_rect_02 @ R_rect_00 @ T_velo_to_cam`.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.geometry.transforms import invert
from app.io.images import image_size
from app.io.kitti_calib import matrix_3x4, read_calib_file, rectifying_4x4, require, rigid_from_r_t
from app.io.las import las_point_count, read_las_points
from app.io.odometry import estimated_poses
from app.io.oxts import imu_poses, read_oxts_packet
from app.io.survey import Camera, Frame, PointCloud, Survey
from app.io.velodyne_bin import bin_point_count, check_finite, read_velodyne_bin

CAMERA = "image_02"
CALIB_FILES = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt")


def find_sync_folder(source: Path) -> Path:
    if (source / "velodyne_points").is_dir():
        return source
    candidates = sorted(p.parent for p in source.glob("*/velodyne_points") if p.is_dir())
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise InputError(source, "no velodyne_points folder: not a KITTI raw sync drive")
    raise InputError(source, f"holds {len(candidates)} drives; give one sync folder")


def find_calib_folder(sync: Path) -> Path | None:
    """The folder holding calib_cam_to_cam.txt, searched upwards from the drive."""
    for parent in [sync, *list(sync.parents)[:4]]:
        if (parent / CALIB_FILES[0]).is_file():
            return parent
        for sibling in sorted(parent.glob(f"*_calib/*/{CALIB_FILES[0]}")):
            return sibling.parent
    return None


def read_timestamps(path: Path, expected: int) -> np.ndarray | None:
    """Seconds since the epoch from a KITTI `timestamps.txt` (YYYY-MM-DD hh:mm:ss.fffffffff)."""
    if not path.is_file():
        return None
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    try:
        stamps = np.array([ln.replace(" ", "T") for ln in lines], dtype="datetime64[ns]")
    except ValueError:
        raise InputError(path, "timestamps are not 'YYYY-MM-DD hh:mm:ss.fffffffff' lines") from None
    if len(stamps) < expected:
        raise InputError(path, f"has {len(stamps)} timestamps for {expected} frames")
    return stamps[:expected].astype(np.int64) * 1e-9


def read_camera(calib_dir: Path, image_files: list[Path]) -> tuple[Camera, np.ndarray]:
    """The image_02 camera and T_velo_imu (4x4, imu -> velodyne)."""
    cam_path = calib_dir / CALIB_FILES[0]
    cam = read_calib_file(cam_path)
    P = matrix_3x4(cam, "P_rect_02", cam_path)
    R_rect = rectifying_4x4(cam, "R_rect_00", cam_path)
    T_cam_velo = rigid_from_r_t(calib_dir / CALIB_FILES[1])
    T_velo_imu = rigid_from_r_t(calib_dir / CALIB_FILES[2])
    if "S_rect_02" in cam:
        width, height = (int(v) for v in require(cam, "S_rect_02", 2, cam_path))
    elif image_files:
        width, height = image_size(image_files[0])
    else:
        raise InputError(cam_path, "calibration entry S_rect_02 is missing and there are no images")
    camera = Camera(CAMERA, P, R_rect @ T_cam_velo, width, height, "P_rect_02")
    return camera, T_velo_imu


LAZ_INTENSITY_SCALE = 65535.0  # reflectance 0..1 <-> LAS uint16 intensity


def read_laz_scan(path: Path) -> PointCloud:
    """A scan stored as LAZ (sensor frame, gps_time = per-point time), reflectance back to 0..1."""
    cloud = read_las_points(path)
    check_finite(path, cloud.xyz)
    if cloud.intensity is not None:
        cloud.intensity = cloud.intensity / np.float32(LAZ_INTENSITY_SCALE)
    return PointCloud(cloud.xyz, cloud.intensity, cloud.time)


def read_kitti_raw(source: Path) -> Survey:
    sync = find_sync_folder(source)
    scan_dir = sync / "velodyne_points" / "data"
    scan_files = sorted(scan_dir.glob("*.bin")) or sorted(scan_dir.glob("*.laz"))
    if not scan_files:
        raise InputError(scan_dir, "contains no .bin (or .laz) scans")
    compressed = scan_files[0].suffix == ".laz"
    counts = [las_point_count(f) if compressed else bin_point_count(f) for f in scan_files]
    n = len(scan_files)

    image_dir = sync / CAMERA / "data"
    images = {p.stem: p for p in image_dir.glob("*.png")} if image_dir.is_dir() else {}
    calib_dir = find_calib_folder(sync)
    if calib_dir is None:
        raise InputError(sync, f"no {CALIB_FILES[0]} found beside or above the drive")
    camera, T_velo_imu = read_camera(calib_dir, [images[k] for k in sorted(images)])

    oxts_dir = sync / "oxts" / "data"
    oxts_files = sorted(oxts_dir.glob("*.txt")) if oxts_dir.is_dir() else []
    if oxts_files:
        if len(oxts_files) < n:
            raise InputError(oxts_dir, f"has {len(oxts_files)} OXTS packets for {n} scans")
        packets = np.stack([read_oxts_packet(f) for f in oxts_files[:n]])
        poses = imu_poses(packets) @ invert(T_velo_imu)  # velodyne -> world
        estimated = False
    else:
        poses = estimated_poses(scan_files)
        estimated = True

    velo = sync / "velodyne_points"
    times = read_timestamps(velo / "timestamps.txt", n)
    if times is None:
        times = read_timestamps(sync / "oxts" / "timestamps.txt", n)
    starts = read_timestamps(velo / "timestamps_start.txt", n)
    ends = read_timestamps(velo / "timestamps_end.txt", n)
    sweeps = (
        list(zip(starts, ends, strict=True)) if starts is not None and ends is not None else None
    )
    frames = [
        Frame(
            index=i,
            frame_id=f.stem,
            pose=poses[i],
            timestamp=None if times is None else float(times[i]),
            point_count=counts[i],
            source_path=f,
            image_paths={CAMERA: images[f.stem]} if f.stem in images else {},
            _load_points=partial(read_laz_scan, f)
            if compressed
            else partial(read_velodyne_bin, f, *(sweeps[i] if sweeps else ())),
        )
        for i, f in enumerate(scan_files)
    ]
    return Survey(
        name=sync.name,
        source=sync,
        format="kitti-raw",
        frames=frames,
        cameras={CAMERA: camera},
        poses_estimated=estimated,
        scanner="hdl64",
    )
