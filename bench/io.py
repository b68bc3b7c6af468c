"""Read one ~120k-point KITTI frame and project it into its camera image (target <= 20 ms).

Baseline, measured in the same run: the textbook KITTI devkit way, homogeneous coordinates and
the three calibration matrices applied one after another (`P2 @ R0 @ Tr @ X_h`), on a scan read
with the same np.fromfile. mmsclean folds the matrices into one 3x4 once and does a single
float64 matmul over the points.

Usage: python -m bench.io [--repeats 50] [--no-record]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from app.geometry.projection import project
from app.io import open_survey
from bench.common import append_results, markdown_table, median_ms


def devkit_projection(path: Path, P: np.ndarray, R0: np.ndarray, Tr: np.ndarray, w: int, h: int):
    scan = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    xyz_h = np.hstack([scan[:, :3].astype(np.float64), np.ones((len(scan), 1))]).T  # 4 x N
    cam = R0 @ (Tr @ xyz_h)
    uvw = P @ cam
    uv = uvw[:2] / uvw[2]
    return (uvw[2] > 0.1) & (uv[0] >= 0) & (uv[0] < w) & (uv[1] >= 0) & (uv[1] < h)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    args = parser.parse_args()

    real = os.environ.get("MMSCLEAN_REAL_DATA")
    if not real:
        print("MMSCLEAN_REAL_DATA is not set: this benchmark needs the real KITTI sample")
        return 2
    survey = open_survey(Path(real) / "semantickitti/sequences/04", "semantickitti")
    frame = survey.frames[0]
    camera = survey.cameras["image_2"]
    path = frame.source_path

    def mmsclean_read_and_project():
        cloud = frame.points()
        return project(cloud.xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)

    R0 = np.eye(4)  # odometry calibration: Tr already maps to rectified cam0
    ours = mmsclean_read_and_project()
    base = devkit_projection(path, camera.P, R0, camera.T_cam_sensor, camera.width, camera.height)
    assert np.array_equal(ours.in_image, base), "the two projections disagree"

    t_ours = median_ms(mmsclean_read_and_project, args.repeats)
    t_read = median_ms(frame.points, args.repeats)
    t_base = median_ms(
        lambda: devkit_projection(
            path, camera.P, R0, camera.T_cam_sensor, camera.width, camera.height
        ),
        args.repeats,
    )
    rows = [
        ["devkit baseline (homogeneous, 3 matmuls)", f"{t_base:.2f}", "1.00x"],
        ["mmsclean read + project", f"{t_ours:.2f}", f"{t_base / t_ours:.2f}x"],
        ["  of which read (Frame.points)", f"{t_read:.2f}", ""],
    ]
    table = markdown_table(["step (frame 000000 of seq 04)", "median ms", "speed-up"], rows)
    print(
        f"{len(ours.depth):,} points, {int(ours.in_image.sum()):,} in image_2, "
        f"{args.repeats} repeats"
    )
    print(table)
    verdict = "meets" if t_ours <= 20 else "misses"
    print(f"target <= 20 ms: {verdict}")
    if not args.no_record:
        append_results(
            "I/O: read one KITTI frame and project it into its image",
            "MMSCLEAN_REAL_DATA=../shared/data .venv/bin/python -m bench.io",
            table,
            f"{len(ours.depth):,} points; target <= 20 ms: {verdict}.",
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
