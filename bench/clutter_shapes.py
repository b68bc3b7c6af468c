"""The clutter pipeline's vehicle shape classifier (`app/pipelines/clutter/shapes.py`) cluster by
cluster: on simulated streets it never trained on and on real SemanticKITTI 04 / 05 / 08.

Every trackable, object-sized cluster of a frame (the pipeline's clustering and ClutterConfig's
defaults; `training/shapes.py` picks and labels them: vehicle when >= 70 % of its scored points
are a SemanticKITTI vehicle, other when <= 30 %), scored at P >= 0.5 (the training threshold)
and at the pipeline's `min_vehicle_shape` (a track's mean over its frames must reach it). Recall
per kind: cars (10, 252) apart from the other vehicles (trucks, buses, trailers, site machines,
caravans: 13, 16, 18, 20, 256-259). Several checkpoints side by side in one run.

With `--loso SEEDS`, each real sequence is also scored by a network trained here on the
simulated streets of SEEDS and the *other* real sequences (leave-one-sequence-out; `mmsclean
train clutter-shapes --semantickitti` would train on all of them), so a real row never scores a
network that saw its sequence.

Usage: python -m bench.clutter_shapes [--models a.pt,b.pt] [--sim-seeds 336-349]
[--scenes a,b,...] [--vegetation] [--sequences 04,05,08] [--loso 401-470] [--no-record].
Real rows need MMSCLEAN_REAL_DATA.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from app.cli.common import seed_list
from app.io import open_survey
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.shapes import ROTATING_MODEL, ShapeInputs, load_vehicle_shapes
from app.pipelines.clutter.training.shapes import (
    SCENES,
    labelled_samples,
    samples,
    scene_cycle,
    street_samples,
    train_shapes,
    with_real,
)
from bench.common import append_results, markdown_table

COMMAND = (
    "MMSCLEAN_REAL_DATA=../shared/data MMSCLEAN_DATA_DIR=/tmp/mmsvar "
    ".venv/bin/python -m bench.clutter_shapes"
)
CARS = (10, 252)
# seeds no shipped checkpoint trained or validated on (the CLI's defaults end at 335)
HELD_OUT_SEEDS = "336-349"


def scores(probability: np.ndarray, y: np.ndarray, classes: np.ndarray, threshold: float) -> list:
    said = probability >= threshold
    truth = y.astype(bool)
    car = truth & np.isin(classes, CARS)
    other_vehicle = truth & ~car

    def share(part: np.ndarray, of: np.ndarray) -> str:
        return f"{100.0 * part.sum() / of.sum():.1f}" if of.any() else "-"

    return [
        share(said & truth, said),
        share(said & truth, truth),
        share(said & car, car),
        share(said & other_vehicle, other_vehicle),
    ]


def trained_on(path: Path) -> str:
    """What a checkpoint's card says it learnt from, in one phrase."""
    card = load_vehicle_shapes(path).card
    sim = card.get("simulation", {})
    seeds = sim.get("seeds") or [0]
    real = (card.get("real") or {}).get("sequences") or []
    return (
        f"{path.name}: simulated seeds {min(seeds)}-{max(seeds)}, scenes "
        f"{', '.join(sim.get('scenes', []))}"
        + (" with hedges and bushes" if sim.get("vegetation") else "")
        + (f", real {'+'.join(real)}" if real else "")
    )


def row(model: str, scored_on: str, p: np.ndarray, y: np.ndarray, classes: np.ndarray) -> list:
    car = y.astype(bool) & np.isin(classes, CARS)
    return [
        model, f"{len(y):,}", scored_on, f"{int(y.sum()):,}", f"{int(car.sum()):,}",
        f"{int(y.sum() - car.sum()):,}", *scores(p, y, classes, 0.5),
        *scores(p, y, classes, ClutterConfig().min_vehicle_shape),
    ]  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--models", default=str(ROTATING_MODEL), help="checkpoints, comma separated"
    )
    parser.add_argument("--sim-seeds", default=HELD_OUT_SEEDS)
    parser.add_argument("--sequences", default="04,05,08")
    parser.add_argument("--loso", default="", help="simulated seeds of the LOSO networks")
    parser.add_argument("--scenes", default=",".join(SCENES), help="the scene cycle of both")
    parser.add_argument("--vegetation", action="store_true", help="both with hedges, bushes")
    parser.add_argument("--real-weight", type=float, default=10.0)
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    threshold = ClutterConfig().min_vehicle_shape
    scenes = scene_cycle(args.scenes)
    sets: list[tuple[str, ShapeInputs, np.ndarray, np.ndarray]] = []
    seeds = seed_list("--sim-seeds", args.sim_seeds)
    if seeds:
        sets.append(
            (
                f"simulated, seeds {args.sim_seeds}",
                *samples(seeds, scenes=scenes, vegetation=args.vegetation),
            )
        )
    real = os.environ.get("MMSCLEAN_REAL_DATA")
    names = [s.strip() for s in args.sequences.split(",") if s.strip()]
    if names and not real:
        print("MMSCLEAN_REAL_DATA is not set: real rows left out")
        names = []
    surveys = {
        name: open_survey(Path(real) / "semantickitti" / "sequences" / name, "semantickitti")
        for name in names
    }
    for name, survey in surveys.items():
        sets.append((f"real SemanticKITTI {name}", *street_samples(survey, step=1)))
    header = [
        "model", "clusters", "scored on", "vehicles", "cars", "other vehicles",
        "precision @0.5", "recall @0.5", "car recall @0.5", "other-vehicle recall @0.5",
        f"precision @{threshold:g}", f"recall @{threshold:g}", f"car recall @{threshold:g}",
        f"other-vehicle recall @{threshold:g}",
    ]  # fmt: skip
    rows = []
    for path in filter(None, (p.strip() for p in args.models.split(","))):
        model = load_vehicle_shapes(Path(path))
        for name, inputs, y, classes in sets:
            rows.append(row(Path(path).name, name, model.probability(inputs), y, classes))
    if args.loso:
        simulated = samples(
            seed_list("--loso", args.loso), scenes=scenes, vegetation=args.vegetation
        )
        for name, inputs, y, classes in sets[len(sets) - len(surveys) :]:
            held_out = name.rsplit(" ", 1)[1]
            others = [n for n in surveys if n != held_out]
            real_samples = labelled_samples([surveys[n] for n in others])
            x, target, weight = with_real(simulated, real_samples, args.real_weight)
            model = train_shapes(x, target, args.epochs, weight=weight)
            label = f"LOSO: sim {args.loso} + real {'+'.join(others)}"
            rows.append(row(label, name, model.probability(inputs), y, classes))
    table = markdown_table(header, rows)
    notes = (
        "Per cluster of a frame (a track averages its frames). Simulated rows are synthetic: "
        f"HDL-64E-like streets of seeds {args.sim_seeds} (scanner varied per seed, every second "
        f"frame, scenes in turn: {', '.join(scenes)}), seeds no checkpoint here trained or "
        "validated on. Real rows: SemanticKITTI's ten frames per sequence (HDL-64E), every "
        "frame. Precision: of the clusters called vehicle, the share that are; recall: of the "
        "vehicle clusters, the share called vehicle. Checkpoints (their cards): "
        + "; ".join(trained_on(Path(p)) for p in filter(None, args.models.split(",")))
        + (
            f". LOSO rows: a network trained in this run on the simulated streets of seeds "
            f"{args.loso} (the same scene cycle) and the other real sequences' clusters, each "
            f"weighing {args.real_weight:g} simulated ones, {args.epochs} epochs."
            if args.loso
            else "."
        )
    )
    print(f"\n{table}\n\n{notes}")
    if not args.no_record:
        command = (
            f"{COMMAND} --models {args.models} --sim-seeds {args.sim_seeds} --scenes "
            f"{args.scenes} --sequences {args.sequences}"
            + (" --vegetation" if args.vegetation else "")
            + (f" --loso {args.loso} --real-weight {args.real_weight:g}" if args.loso else "")
        )
        append_results("Clutter: vehicle shapes per cluster", command, table, notes)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
