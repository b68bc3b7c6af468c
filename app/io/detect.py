"""Tell a survey's format from what is on disk, for imports and uploads that do not name it.

Checked in this order, because the simulator writes a KITTI-raw-like folder plus ground truth:

- a file: `.las` / `.laz` -> las, `.ply` -> ply, `.pcd` -> pcd;
- a folder with `ground_truth/simulation.json` -> sim;
- a folder with `velodyne/`, `calib.txt` and `poses.txt` -> semantickitti;
- a folder with `velodyne_points/` (itself, or a drive one or two levels down, as KITTI's
  `<date>/<date>_drive_NNNN_sync/` downloads unpack) -> kitti-raw.
"""

from __future__ import annotations

from pathlib import Path

from app.core.errors import InputError

FILE_SUFFIXES = {".las": "las", ".laz": "las", ".ply": "ply", ".pcd": "pcd"}


def detect_format(path: str | Path) -> str:
    """The reader name for PATH; InputError naming PATH when nothing matches."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "does not exist")
    if path.is_file():
        fmt = FILE_SUFFIXES.get(path.suffix.lower())
        if fmt is None:
            known = ", ".join(sorted(FILE_SUFFIXES))
            raise InputError(
                path,
                f"cannot tell the format of a {path.suffix or 'plain'} file "
                f"(known: {known}); name the format",
            )
        return fmt
    if (path / "ground_truth" / "simulation.json").is_file():
        return "sim"
    if (path / "velodyne").is_dir() and (path / "calib.txt").is_file():
        if (path / "poses.txt").is_file():
            return "semantickitti"
        raise InputError(path, "has velodyne/ and calib.txt but no poses.txt (SemanticKITTI)")
    for pattern in ("velodyne_points", "*/velodyne_points", "*/*/velodyne_points"):
        if any(p.is_dir() for p in path.glob(pattern)):
            return "kitti-raw"
    raise InputError(
        path,
        "cannot tell the format: expected ground_truth/simulation.json (sim), velodyne/ + "
        "calib.txt + poses.txt (semantickitti) or velodyne_points/ (kitti-raw); name the format",
    )
