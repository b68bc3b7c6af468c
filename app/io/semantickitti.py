"""Reader for SemanticKITTI / KITTI odometry sequences (format `semantickitti`).

Layout: `velodyne/NNNNNN.bin`, `labels/NNNNNN.label` (uint32: semantic = l & 0xFFFF, instance =
l >> 16), `image_0..3/NNNNNN.png`, `calib.txt` (P0..P3 3x4, Tr velodyne -> rectified cam0),
`poses.txt` (cam0 -> world per frame of the full sequence), `times.txt` (seconds).

The frame number is the file stem, so a partial copy (frames 0-9 of a long sequence) picks its own
rows of poses.txt and times.txt. Velodyne -> world for frame i is `inv(Tr) @ pose_i @ Tr`.
Labels are reference data for evaluation only.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.geometry.transforms import from_3x4, invert
from app.io.images import image_size
from app.io.kitti_calib import matrix_3x4, read_calib_file, rigid_4x4
from app.io.survey import Camera, Frame, Survey
from app.io.velodyne_bin import bin_point_count, read_velodyne_bin

CAMERAS = {"image_0": "P0", "image_1": "P1", "image_2": "P2", "image_3": "P3"}


def read_pose_rows(path: Path, frame_numbers: list[int]) -> np.ndarray:
    """(F, 4, 4) cam0 -> world poses of the given frame numbers from a KITTI poses.txt."""
    if not path.is_file():
        raise InputError(path, "poses file is missing")
    try:
        rows = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise InputError(path, f"is not a table of numbers ({exc})") from None
    if rows.shape[1] != 12:
        raise InputError(path, f"has {rows.shape[1]} values per line, expected 12 (3x4 pose)")
    if len(rows) <= max(frame_numbers):
        raise InputError(
            path, f"has {len(rows)} poses, fewer than the frames (up to frame {max(frame_numbers)})"
        )
    if not np.isfinite(rows).all():
        raise InputError(path, "contains NaN or infinite values")
    return np.stack([from_3x4(rows[i]) for i in frame_numbers])


def read_times(path: Path, frame_numbers: list[int]) -> np.ndarray | None:
    if not path.is_file():
        return None
    try:
        times = np.loadtxt(path, dtype=np.float64, ndmin=1)
    except ValueError as exc:
        raise InputError(path, f"is not a column of seconds ({exc})") from None
    if times.ndim != 1 or len(times) <= max(frame_numbers):
        raise InputError(path, f"has {len(times)} times, fewer than the frames")
    return times[frame_numbers]


def label_bytes(semantic: np.ndarray, instance: np.ndarray) -> bytes:
    """A `.label` file's bytes: per point a little-endian uint32, the semantic id in the lower
    16 bits and the instance id in the upper 16 (what `read_label_file` reads back)."""
    semantic, instance = np.asarray(semantic), np.asarray(instance)
    if semantic.shape != instance.shape or semantic.ndim != 1:
        raise ValueError(f"semantic {semantic.shape} and instance {instance.shape}: one per point")
    for name, values in (("semantic", semantic), ("instance", instance)):
        if values.size and (values.min() < 0 or values.max() > 0xFFFF):
            raise ValueError(f"{name} ids must lie in 0..65535")
    words = semantic.astype(np.uint32) | (instance.astype(np.uint32) << 16)
    return words.astype("<u4", copy=False).tobytes()


def read_label_file(path: Path, point_count: int) -> dict[str, np.ndarray]:
    size = path.stat().st_size
    if size != 4 * point_count:
        raise InputError(path, f"has {size // 4} labels for {point_count} points")
    raw = np.fromfile(path, dtype="<u4")
    return {"semantic": (raw & 0xFFFF).astype(np.uint16), "instance": (raw >> 16).astype(np.uint16)}


def read_semantickitti(source: Path) -> Survey:
    scan_files = sorted((source / "velodyne").glob("*.bin"))
    if not scan_files:
        raise InputError(
            source / "velodyne", "contains no .bin scans: not a SemanticKITTI sequence"
        )
    try:
        numbers = [int(f.stem) for f in scan_files]
    except ValueError:
        raise InputError(
            source / "velodyne", "scan names must be frame numbers (000123.bin)"
        ) from None
    counts = [bin_point_count(f) for f in scan_files]

    calib_path = source / "calib.txt"
    calib = read_calib_file(calib_path)
    T_cam0_velo = rigid_4x4(calib, "Tr", calib_path)
    projections = {
        key: matrix_3x4(calib, key, calib_path) for key in CAMERAS.values() if key in calib
    }
    cameras: dict[str, Camera] = {}
    images: dict[str, dict[str, Path]] = {}
    for folder, key in CAMERAS.items():
        files = {p.stem: p for p in (source / folder).glob("*.png")}
        if not files:
            continue
        if key not in projections:
            raise InputError(calib_path, f"calibration entry {key} is missing (needed by {folder})")
        P = projections[key]
        width, height = image_size(next(iter(files.values())))
        cameras[folder] = Camera(folder, P, T_cam0_velo, width, height, key)
        images[folder] = files

    cam_poses = read_pose_rows(source / "poses.txt", numbers)
    poses = invert(T_cam0_velo) @ cam_poses @ T_cam0_velo
    times = read_times(source / "times.txt", numbers)

    label_dir = source / "labels"
    has_labels = label_dir.is_dir() and any(label_dir.glob("*.label"))
    frames = []
    for i, (f, count) in enumerate(zip(scan_files, counts, strict=True)):
        label_file = label_dir / f"{f.stem}.label"
        frames.append(
            Frame(
                index=i,
                frame_id=f.stem,
                pose=poses[i],
                timestamp=None if times is None else float(times[i]),
                point_count=count,
                source_path=f,
                image_paths={c: files[f.stem] for c, files in images.items() if f.stem in files},
                _load_points=partial(read_velodyne_bin, f),
                _load_reference=partial(read_label_file, label_file, count)
                if label_file.is_file()
                else None,
            )
        )
    return Survey(
        name=f"semantickitti-{source.name}",
        source=source,
        format="semantickitti",
        frames=frames,
        cameras=cameras,
        reference_label_kinds=("semantic", "instance") if has_labels else (),
        scanner="hdl64",
    )
