"""Phantom pipeline benchmarks (issue 4). Each part prints a table and appends it to RESULTS.md.

  speed     dense vs per-window inference on a >= 1M-point simulated map, same run: pillars/s
            of both, speed-up, label agreement
  memory    peak resident memory of a whole run on a ~10M-point simulated map (own process)
  accuracy  held-out simulated surveys (seeds never used in training): Table I per class and
            Table II with both baselines
  validation  whole validation maps (seeds 111-113), the figures models and settings are
            chosen by
  kitti     SemanticKITTI 04 / 05 / 08 (10 posed frames accumulated), leave-one-sequence-out,
            rotating scanner: per held-out sequence (--kitti-held) and training data
            (--kitti-sources: sim = simulated HDL-64E drives, real = the two other sequences,
            sim+real); --passes adds time as evidence (distinct scanner passes per voxel)
  rotating-sim  a rotating-scanner model (--model) on held-out simulated drives (seeds
            691-693, scanners drawn from the seed), cut into 10-frame maps
  train     training time on 40k pillars (10k per class) to the paper's validation F; writes the
            checkpoint (--model; default the shipped file of the network trained: --context 16, the
            default, or --context 0 for the paper network); --sim-seeds chooses the maps
  profile-time  time as evidence on a profile scanner: two networks trained alike (seeds
            101-112 or --sim-seeds, --kitti-per-class, --kitti-epochs), with and without the
            passes channel, scored on the held-out surveys 201-203

Usage: python -m bench.phantom PART [--model PATH] [--context N] [--no-record]
Simulated maps are synthetic (app.simulate); they are cached under $MMSCLEAN_DATA_DIR/cache.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from app.core.settings import get_settings
from app.io import open_survey
from app.simulate.survey import SimulationConfig, simulate
from bench.common import append_results, markdown_table

COMMAND = "MMSCLEAN_DATA_DIR=/tmp/mmsvar .venv/bin/python -m bench.phantom"


def simulated(
    scene: str, length: float, seed: int, scanner: str = "profile", speed: float | None = None
) -> Path:
    """A cached simulated survey (deterministic: reused when it exists); `speed` fixes the
    survey vehicle's speed (m/s) instead of the seed's."""
    name = f"{scene}-{length:g}m-{scanner}-seed{seed}" + ("" if speed is None else f"-{speed:g}ms")
    folder = get_settings().cache_dir / "bench" / name
    if not folder.is_dir():
        config = SimulationConfig(scene=scene, length=length, seed=seed, scanner=scanner,
                                  camera=False, write_map=False, drive_speed=speed)  # fmt: skip
        simulate(config, folder)
    return folder


def part_speed(args) -> tuple[str, str, str]:
    from app.geometry.ground import estimate_ground
    from app.io.accumulate import accumulate
    from app.pipelines.phantom.classify import classify_dense, classify_windows
    from app.pipelines.phantom.config import PhantomConfig
    from app.pipelines.phantom.model import load_model
    from app.pipelines.phantom.pillars import build_pillar_map

    survey = open_survey(simulated("mixed", 100.0, 301), "sim")
    amap = accumulate(survey, with_reference=False)
    cfg = PhantomConfig()
    pm = build_pillar_map(amap.xyz, estimate_ground(amap.xyz), cfg)
    net, _ = load_model(args.model)
    t0 = time.perf_counter()
    dense = classify_dense(net, pm, cfg.tile_pillars)
    t_dense = time.perf_counter() - t0
    t0 = time.perf_counter()
    windows = classify_windows(net, pm, cfg.batch_size)
    t_windows = time.perf_counter() - t0
    agree = float((dense.argmax(1) == windows.argmax(1)).mean())
    n = len(pm.pillars)
    rows = [
        ["per-window (reference)", f"{t_windows:.1f}", f"{n / t_windows:,.0f}", "1.0x"],
        ["dense, tiled", f"{t_dense:.2f}", f"{n / t_dense:,.0f}", f"{t_windows / t_dense:.1f}x"],
    ]
    table = markdown_table(["path", "seconds", "pillars/s", "speed-up"], rows)
    notes = (
        f"Synthetic map: mixed street 100 m, profile scanner, seed 301: {len(amap.xyz):,} points, "
        f"{n:,} occupied pillars. Label agreement dense vs per-window: {agree:.4%}; "
        f"max probability difference {np.abs(dense - windows).max():.1e}."
    )
    return "Phantom: dense vs per-window inference", table, notes


def part_memory(args) -> tuple[str, str, str]:
    folder = simulated("mixed", 600.0, 302)
    out = get_settings().cache_dir / "bench" / "phantom-memory-out"
    code = (
        "import json, resource, sys, time\n"
        "from app.io import open_survey\n"
        "from app.pipelines.phantom.run import run_phantom_to_folder\n"
        "t = time.perf_counter()\n"
        f"r = run_phantom_to_folder(open_survey({str(folder)!r}, 'sim'), {str(out)!r}, "
        f"model_path={str(args.model) if args.model else None!r})\n"
        "peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "print(json.dumps({'points': r['counts']['points'], 'seconds': time.perf_counter() - t,"
        " 'peak_kb': peak, 'timings': r['timings']}))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    stats = json.loads(done.stdout.strip().splitlines()[-1])
    peak_gb = stats["peak_kb"] / 1024**2
    rows = [
        ["points", f"{stats['points']:,}"],
        ["peak resident memory", f"{peak_gb:.2f} GB (target <= 4 GB)"],
        ["wall time (with evaluation and LAZ output)", f"{stats['seconds']:.1f} s"],
    ] + [[f"  {k}", f"{v:.1f} s"] for k, v in stats["timings"].items()]
    table = markdown_table(["measure", "value"], rows)
    return "Phantom: peak memory on a ~10M-point map", table, "Synthetic: mixed 600 m, seed 302."


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "part",
        choices=[
            "speed",
            "memory",
            "accuracy",
            "validation",
            "kitti",
            "rotating-sim",
            "train",
            "profile-time",
        ],  # fmt: skip
    )
    parser.add_argument("--model", type=Path, default=None, help="checkpoint (default: shipped)")
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument("--epochs", type=int, default=10, help="train: epochs")
    parser.add_argument(
        "--context", type=int, default=16, help="train, kitti: context-branch channels (0: paper)"
    )
    parser.add_argument(
        "--sim-seeds", default="", help="train: simulator seeds, comma separated (default: 36)"
    )
    parser.add_argument("--kitti-per-class", type=int, default=4000, help="kitti: pillars/class")
    parser.add_argument("--kitti-epochs", type=int, default=6, help="kitti: epochs per model")
    parser.add_argument(
        "--kitti-sources",
        default="real",
        help="kitti: training data per held-out sequence, comma separated runs of "
        "sim (simulated HDL-64E drives), real (the other sequences), sim+real",
    )
    parser.add_argument("--kitti-held", default="04,05,08", help="kitti: sequences to hold out")
    parser.add_argument(
        "--passes", action="store_true", help="kitti: time as evidence (scanner passes channel)"
    )
    parser.add_argument("--kitti-sim-seeds", type=int, default=12, help="kitti: HDL-64E drives")
    parser.add_argument("--keep-models", default="", help="kitti: copy the trained models here")
    args = parser.parse_args()
    parts = {"speed": part_speed, "memory": part_memory}
    if args.part not in parts:
        from bench import phantom_quality

        parts.update(phantom_quality.PARTS)
    title, table, notes = parts[args.part](args)
    print(table)
    print(notes)
    if not args.no_record:
        append_results(title, f"{COMMAND} {' '.join(sys.argv[1:])}", table, notes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
