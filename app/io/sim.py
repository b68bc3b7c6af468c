"""Reader for simulator output (format `sim`): the KITTI-raw-like sensor part plus ground truth.

Poses come from `poses.txt` (sensor -> world in the simulation's world frame, as the GNSS/INS
measured them: noisy when the simulation added pose noise); the exact ones are in
`ground_truth/poses.txt`. Per-point times and the reference labels (semantic, instance, moving,
pillar class, guardrail index and part, halo) come from `ground_truth/labels/NNNNNNNNNN.npz`.
"""

from __future__ import annotations

import json
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.io.kitti_raw import read_kitti_raw, read_laz_scan
from app.io.point_files import guarded
from app.io.survey import PointCloud, Survey
from app.io.velodyne_bin import read_velodyne_bin

REFERENCE_KINDS = ("semantic", "instance", "moving", "pillar_class", "guardrail", "part", "halo")


def read_pose_file(path: Path, count: int) -> np.ndarray:
    """(count, 4, 4) poses from a file of row-major 3x4 rows."""
    if not path.is_file():
        raise InputError(path, "poses file is missing")
    rows = guarded(path, "poses", lambda: np.loadtxt(path, dtype=np.float64, ndmin=2))
    if rows.shape[1] != 12:
        raise InputError(path, f"has {rows.shape[1]} values per line, expected 12 (3x4 pose)")
    if len(rows) < count:
        raise InputError(path, f"has {len(rows)} poses for {count} frames")
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :4] = rows[:count].reshape(-1, 3, 4)
    return poses


def read_truth(
    path: Path, point_count: int, names: tuple[str, ...] | None = None
) -> dict[str, np.ndarray]:
    """The frame's ground-truth arrays (`names` only: each is a compressed member, and a
    frame's points need only its times)."""
    if not path.is_file():
        raise InputError(path, "ground-truth labels are missing")
    with guarded(path, "ground truth", lambda: np.load(path)) as data:
        missing = [n for n in names or () if n not in data.files]
        if missing:
            raise InputError(path, f"has no {', '.join(missing)}")
        wanted = data.files if names is None else names
        arrays = guarded(path, "ground truth", lambda: {name: data[name] for name in wanted})
    for name, values in arrays.items():
        if len(values) != point_count:
            raise InputError(path, f"{name} has {len(values)} entries for {point_count} points")
    return arrays


def _load_points(scan: Path, truth: Path) -> PointCloud:
    """Scan points with their exact per-point times (in the LAZ scan, or in the truth file)."""
    if scan.suffix == ".laz":
        return read_laz_scan(scan)
    cloud = read_velodyne_bin(scan)
    cloud.time = read_truth(truth, len(cloud), ("time",))["time"]
    return cloud


def _load_reference(truth: Path, point_count: int) -> dict[str, np.ndarray]:
    return read_truth(truth, point_count, REFERENCE_KINDS)


def read_sim(source: Path) -> Survey:
    info_path = source / "ground_truth" / "simulation.json"
    if not info_path.is_file():
        raise InputError(source, "no ground_truth/simulation.json: not a simulator output folder")
    info = json.loads(info_path.read_text())
    survey = read_kitti_raw(source)
    poses = read_pose_file(source / "poses.txt", len(survey))
    label_dir = source / "ground_truth" / "labels"
    frames = [
        replace(
            frame,
            pose=poses[i],
            _load_points=partial(
                _load_points, frame.source_path, label_dir / f"{frame.frame_id}.npz"
            ),
            _load_reference=partial(
                _load_reference, label_dir / f"{frame.frame_id}.npz", frame.point_count
            ),
        )
        for i, frame in enumerate(survey.frames)
    ]
    return replace(
        survey,
        name=info.get("name", source.name),
        source=source,
        format="sim",
        frames=frames,
        poses_estimated=False,
        reference_label_kinds=REFERENCE_KINDS,
        scanner=info.get("scanner"),
        scanner_params=info.get("scanner_params"),
    )
