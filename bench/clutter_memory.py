"""What a clutter tile's worker holds, by the points it reads: the measurements behind a
`run:clutter` job's memory estimate (`app/jobs/clutter_tasks.py`: bytes per point of a tile,
the segmentation network) and the default tile length.

Simulated: the mixed profile-scanner survey (0.5 km, seed 901, 9.5 m/s) cut into tiles of each
length and run on a fresh local cluster of one worker per length (dynamic mode, one thread);
per length the points the largest tile reads and the worker's peak resident memory. The slope
between the shortest and the longest tiles is the bytes per point read. Real (with
MMSCLEAN_REAL_DATA): SemanticKITTI 04's ten frames in one process, without and with the camera;
the difference is the segmentation network's memory.

Usage: python -m bench.clutter_memory [--lengths 25,50,100,200,400] [--no-record]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

COMMAND = (
    "MMSCLEAN_DATA_DIR=/tmp/mmsvar MMSCLEAN_REAL_DATA=../shared/data "
    "MMSCLEAN_WEIGHTS_DIR=../shared/models .venv/bin/python -m bench.clutter_memory"
)
SURVEY = ("mixed", 500.0, 901, "profile", 9.5)  # scene, metres, seed, scanner, van speed m/s


def simulated_tiles(length: float) -> dict:
    """One run at `length` metres per tile on a fresh one-worker cluster."""
    import tempfile
    from pathlib import Path

    import numpy as np

    from app.core.settings import Settings
    from app.io import open_survey
    from app.io.frame_tiles import FrameTiles
    from app.jobs.cluster import close_clients, tile_client, tile_map
    from app.pipelines.clutter.config import ClutterConfig
    from app.pipelines.clutter.map_budget import frame_map_mb
    from app.pipelines.clutter.run import run_clutter_to_folder
    from app.pipelines.clutter.tiled import TILE_MAP_MB, clutter_halo
    from bench.phantom import simulated

    survey = open_survey(simulated(*SURVEY), "sim")
    sizes = np.array([len(frame.points()) for frame in survey.frames])
    config = ClutterConfig(mode="dynamic", threads=1)
    weights = frame_map_mb(survey, config)
    tiles = FrameTiles.build(survey, length, clutter_halo(config), TILE_MAP_MB, weights, 1)
    settings = Settings(workers=1, sample_dir="")
    tile_client(settings).wait_for_workers(1)
    with tempfile.TemporaryDirectory() as out:
        run_clutter_to_folder(
            survey, Path(out), config, tile_length=length, map_tiles=tile_map(settings)
        )
        summaries = [json.loads(p.read_text()) for p in (Path(out) / "tiles").glob("0*.json")]
    close_clients()
    return {
        "tiles": tiles.count,
        "most_read": max(int(sizes[f].sum()) for f in tiles.frames),
        "peak_mb": max(s["worker_peak_mb"] for s in summaries),
    }


def real_sequence(camera: bool) -> dict:
    """SemanticKITTI 04's frames in this process; its peak resident memory."""
    import resource
    import tempfile
    from pathlib import Path

    from app.io import open_survey
    from app.pipelines.clutter.config import ClutterConfig
    from app.pipelines.clutter.run import run_clutter_to_folder

    real = Path(os.environ["MMSCLEAN_REAL_DATA"]) / "semantickitti" / "sequences" / "04"
    survey = open_survey(real, "semantickitti")
    weights = Path(os.environ.get("MMSCLEAN_WEIGHTS_DIR", "../shared/models"))
    with tempfile.TemporaryDirectory() as out:
        report = run_clutter_to_folder(
            survey, Path(out), ClutterConfig(use_camera=camera, threads=1), weights_dir=weights
        )
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kilobytes
    return {"points": report["counts"]["points"], "frames": len(survey.frames), "peak_mb": peak}


def in_fresh_process(*arguments: str) -> dict:
    command = [sys.executable, "-m", "bench.clutter_memory", *arguments]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lengths", default="25,50,100,200,400")
    parser.add_argument("--length", type=float, help="one simulated run (a fresh process)")
    parser.add_argument("--real", choices=["camera", "no-camera"], help="one real run")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    if args.length is not None:
        print(json.dumps(simulated_tiles(args.length)))
        return 0
    if args.real is not None:
        print(json.dumps(real_sequence(args.real == "camera")))
        return 0
    from bench.common import append_results, markdown_table

    lengths = [float(x) for x in args.lengths.split(",")]
    runs = []
    for length in lengths:
        runs.append(in_fresh_process("--length", str(length)))
        print(json.dumps({"length": length, **runs[-1]}), flush=True)
    rows = [
        [f"{length:g}", str(r["tiles"]), f"{r['most_read']:,}", f"{r['peak_mb']:.0f}"]
        for length, r in zip(lengths, runs, strict=True)
    ]
    low, high = min(runs, key=lambda r: r["most_read"]), max(runs, key=lambda r: r["most_read"])
    spread = high["most_read"] - low["most_read"]
    slope = (high["peak_mb"] - low["peak_mb"]) * 1e6 / spread if spread else float("nan")
    table = markdown_table(["tile m", "tiles", "points the largest tile reads", "peak MB"], rows)
    notes = [
        f"Synthetic: app.simulate {SURVEY[0]} street, {SURVEY[1]:g} m, seed {SURVEY[2]}, "
        f"{SURVEY[3]} scanner at {SURVEY[4]} m/s; dynamic mode, one thread, a fresh one-worker "
        "local cluster per length (tiles also end at the free-space map budget, TILE_MAP_MB). "
        f"Peak growth per point read, shortest to longest reach: {slope:.0f} bytes."
    ]
    if os.environ.get("MMSCLEAN_REAL_DATA"):
        without = in_fresh_process("--real", "no-camera")
        with_camera = in_fresh_process("--real", "camera")
        notes.append(
            f"Real: SemanticKITTI 04, {without['frames']} frames, {without['points']:,} points, "
            f"defaults, one process: {without['peak_mb']:.0f} MB without the camera, "
            f"{with_camera['peak_mb']:.0f} MB with it (the segmentation network: "
            f"{with_camera['peak_mb'] - without['peak_mb']:.0f} MB)."
        )
    print(table)
    print("\n".join(notes))
    if not args.no_record:
        append_results(
            "A clutter tile's memory by the points it reads", COMMAND, table, "\n\n".join(notes)
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
