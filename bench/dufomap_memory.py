"""What frames add to DUFOMap's map, by scanner and street: the measurements behind the clutter
tiles' budget (app/pipelines/clutter/map_budget.py), and that budget's estimate beside them.

Each street's frames are integrated into one `FreeSpaceMap` (0.1 m, one thread) in a fresh
process; the map's memory is the process's resident growth over the integration. Prints a table
and appends it to RESULTS.md.

Streets (synthetic, app.simulate, seed 901): the mixed street's built-up first half and its open
second half (profile scanner, 1 km, 9.5 m/s), a highway (profile, 300 m, 22 m/s), the mixed street
with an HDL-64E-like rotating scanner (150 m, 9.5 m/s).

Usage: python -m bench.dufomap_memory [--frames 200] [--no-record]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

COMMAND = "MMSCLEAN_DATA_DIR=/tmp/mmsvar .venv/bin/python -m bench.dufomap_memory"
# (name, scene, metres, scanner, van speed m/s, first frame)
STREETS = [
    ("town, built-up (mixed, first half)", "mixed", 1000.0, "profile", 9.5, 200),
    ("town, open (mixed, second half)", "mixed", 1000.0, "profile", 9.5, 700),
    ("highway", "highway", 300.0, "profile", 22.0, 0),
    ("town (mixed), rotating scanner", "mixed", 150.0, "hdl64", 9.5, 0),
]


def measure_one(street: int, frames: int) -> dict:
    """Integrate the street's frames; the map's growth, their rays and the budget's estimate."""
    import numpy as np

    from app.io import open_survey
    from app.pipelines.clutter.config import ClutterConfig
    from app.pipelines.clutter.freespace import FreeSpaceMap
    from app.pipelines.clutter.map_budget import frame_map_mb
    from bench.phantom import simulated

    def resident_mb() -> float:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * 4096 / 1e6

    _, scene, metres, scanner, speed, first = STREETS[street]
    survey = open_survey(simulated(scene, metres, 901, scanner, speed), "sim")
    picked = survey.frames[first : first + frames]
    space = FreeSpaceMap(0.1, 0.2, 1, 1, picked[0].pose[:3, 3])
    base, ray_km, points = resident_mb(), 0.0, 0
    for frame in picked:
        xyz = frame.points().xyz
        ray_km += float(np.linalg.norm(xyz, axis=1).sum()) / 1e3
        points += len(xyz)
        space.integrate(xyz, frame.pose)
    grown = resident_mb() - base
    estimate = float(frame_map_mb(survey, ClutterConfig())[first : first + frames].sum())
    return {"frames": len(picked), "points": points, "ray_km": ray_km, "map_mb": grown,
            "estimate_mb": estimate}  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200, help="frames per street")
    parser.add_argument("--street", type=int, default=-1, help="one street (a fresh process)")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    if args.street >= 0:
        print(json.dumps(measure_one(args.street, args.frames)))
        return 0
    from bench.common import append_results, markdown_table

    rows = []
    for k, (name, _, _, scanner, _, _) in enumerate(STREETS):
        command = [sys.executable, "-m", "bench.dufomap_memory", "--street", str(k),
                   "--frames", str(args.frames)]  # fmt: skip
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        r = json.loads(done.stdout.strip().splitlines()[-1])
        rows.append([name, scanner, str(r["frames"]), f"{r['points']:,}", f"{r['ray_km']:,.0f}",
                     f"{r['map_mb']:.0f}", f"{r['map_mb'] / r['ray_km'] * 1e3:.1f}",
                     f"{r['map_mb'] / r['frames']:.2f}", f"{r['estimate_mb']:.0f}",
                     f"{r['estimate_mb'] / r['map_mb']:.2f}"])  # fmt: skip
        print(json.dumps({"street": name, **r}), flush=True)
    table = markdown_table(
        ["street", "scanner", "frames", "points", "ray km", "map MB", "kB per ray km",
         "MB per frame", "budget's estimate MB", "estimate / map"],
        rows,
    )  # fmt: skip
    notes = (
        "Synthetic streets (app.simulate, seed 901). DUFOMap at 0.1 m, d_s 0.2 m, d_p 1, one "
        "thread, as the clutter pipeline's defaults; map MB: the resident growth of a fresh "
        "process over the integration of the street's frames (every point's ray, as the "
        "pipeline integrates them). The budget's estimate: `clutter/map_budget.frame_map_mb` "
        "for the same frames (a profile scanner's ray length, sampled on every 5th frame; a "
        "fixed amount per rotating scanner frame); above 1 it is on the safe side."
    )
    print(table)
    print(notes)
    if not args.no_record:
        append_results("DUFOMap's map per frame: the clutter tiles' budget", COMMAND, table, notes)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
