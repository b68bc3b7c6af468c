"""Surveys of any length (issue 18): the tiled phantom pipeline on simulated surveys of growing
length. Prints a table and appends it to RESULTS.md.

  phantom   per length (--lengths, km): wall time, time per km, peak resident memory of each
            tile worker and of the run's own process (which assembles the outputs); then 1 vs 2
            tile workers on one survey (--speedup-km), same run: the speed-up

Each measurement runs in a fresh process (`one`) with a fresh local Dask cluster, so the peaks
are that run's: a worker's is its whole life (`ru_maxrss`, read on the worker after the run).
Surveys are synthetic (app.simulate, `--scanner` profile or hdl64, scene mixed, seed 901),
cached under $MMSCLEAN_DATA_DIR/cache/bench.

Usage: python -m bench.scale phantom [--lengths 0.25,0.5,1,2,4] [--scanner profile]
       [--workers 2] [--speedup-km 2] [--no-record]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

COMMAND = "MMSCLEAN_DATA_DIR=/tmp/mmsvar .venv/bin/python -m bench.scale"
SEED = 901
SCENE = "mixed"


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kilobytes


def run_one(km: float, scanner: str, workers: int) -> dict:
    """One tiled phantom run on a fresh local cluster of `workers` processes."""
    from app.core.settings import Settings
    from app.io import open_survey
    from app.jobs.cluster import close_clients, tile_client, tile_map
    from app.pipelines.phantom.run import run_phantom_to_folder
    from bench.phantom import simulated

    source = simulated(SCENE, km * 1000.0, SEED, scanner)
    survey = open_survey(source, "sim")
    settings = Settings(workers=workers, sample_dir="")
    with tempfile.TemporaryDirectory() as out:
        client = tile_client(settings)
        client.wait_for_workers(workers)
        started = time.perf_counter()
        report = run_phantom_to_folder(survey, Path(out), map_tiles=tile_map(settings))
        wall = time.perf_counter() - started
        workers_peak = client.run(_peak_rss_mb)
        close_clients()
    tiles = report["tiles"]
    return {
        "km": km,
        "scanner": scanner,
        "workers": workers,
        "points": report["counts"]["points"],
        "tiles": tiles["count"],
        "wall_s": round(wall, 1),
        "worker_peak_mb": round(max(workers_peak.values()), 0),
        "run_peak_mb": round(_peak_rss_mb(), 0),
    }


def measure(km: float, scanner: str, workers: int) -> dict:
    """`run_one` in a fresh process (its own peak memory, its own cluster)."""
    command = [sys.executable, "-m", "bench.scale", "one", "--km", str(km),
               "--scanner", scanner, "--workers", str(workers)]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def part_phantom(args) -> tuple[str, str, str]:
    from app.pipelines.phantom.tiled import TILE_LENGTH
    from bench.common import markdown_table
    from bench.phantom import simulated

    lengths = [float(x) for x in args.lengths.split(",")]
    for km in sorted({*lengths, args.speedup_km}):
        simulated(SCENE, km * 1000.0, SEED, args.scanner)  # simulated before any clock runs
    rows, runs = [], []
    for km in lengths:
        run = measure(km, args.scanner, args.workers)
        runs.append(run)
        rows.append([f"{km:g}", f"{run['points']:,}", str(run["tiles"]), str(args.workers),
                     f"{run['wall_s']:.1f}", f"{run['wall_s'] / km:.1f}",
                     f"{run['worker_peak_mb']:.0f}", f"{run['run_peak_mb']:.0f}"])  # fmt: skip
    per_km = [r["wall_s"] / r["km"] for r in runs]
    spread = (max(per_km) - min(per_km)) / min(per_km) * 100
    table = markdown_table(
        ["km", "points", "tiles", "workers", "wall s", "s per km", "peak MB per tile worker",
         "peak MB run process"],
        rows,
    )  # fmt: skip
    one = measure(args.speedup_km, args.scanner, 1)
    two = measure(args.speedup_km, args.scanner, 2)
    speed = markdown_table(
        ["km", "1 worker s", "2 workers s", "speed-up"],
        [[f"{args.speedup_km:g}", f"{one['wall_s']:.1f}", f"{two['wall_s']:.1f}",
          f"{one['wall_s'] / two['wall_s']:.2f}"]],
    )  # fmt: skip
    notes = (
        f"Synthetic: simulated {args.scanner} surveys (scene {SCENE}, seed {SEED}, no camera), "
        f"phantom pipeline tile by tile ({TILE_LENGTH:g} m tiles, 11 m halo) on a fresh local "
        f"Dask cluster per run, shipped model of the survey's sensor kind. Wall time from the "
        f"start of the run to report.json (tiles, assembly of labels, LAZ and pillars; the "
        f"cluster's start and the simulation not counted). Time per km spread from the "
        f"fastest to the slowest length: {spread:.0f} %. Peak memory: ru_maxrss of each tile "
        f"worker process over its life (it imports torch and the network), and of the "
        f"process that ran the job and assembled the outputs."
    )
    return "Scale: the tiled phantom pipeline by survey length", table + "\n\n" + speed, notes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("part", choices=["phantom", "one"])
    parser.add_argument("--lengths", default="0.25,0.5,1,2,4", help="survey lengths in km")
    parser.add_argument("--scanner", default="profile", choices=["profile", "hdl64"])
    parser.add_argument("--workers", type=int, default=2, help="tile workers")
    parser.add_argument("--speedup-km", type=float, default=2.0)
    parser.add_argument("--km", type=float, default=0.25, help="one: survey length")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    if args.part == "one":
        print(json.dumps(run_one(args.km, args.scanner, args.workers)))
        return 0
    from bench.common import append_results

    title, table, notes = part_phantom(args)
    print(table)
    print(notes)
    if not args.no_record:
        command = f"{COMMAND} phantom --lengths {args.lengths} --scanner {args.scanner}"
        append_results(title, command, table, notes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
