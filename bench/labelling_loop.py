"""The labelling loop, measured (issue 16, part 4): does labelling a new scanner's survey in
the browser and retraining give a better model, and how fast?

An operator is replayed against a real `mmsclean serve` exactly as the viewer writes labels:

1. The survey to label (one real SemanticKITTI sequence, imported through the API from the
   import root) gets a `run:phantom` job: the model's pre-labels and their confidences.
2. The operator asks `GET /surveys/{id}/pillars/uncertain` for the most doubtful areas and, in
   each, brushes round its least confident pillars: every pillar with points within the brush
   radius (the viewer's default, 1 m) is written in one `PUT .../pillars/labels` batch, each pillar
   with its reference class (the sequence's SemanticKITTI labels through the shared pillar
   rule: the operator's answers). A pillar is labelled once.
3. After 500, 1,000, 2,000 and 5,000 labelled pillars, the `train:phantom` job the retraining
   trigger queues (its config, through `POST /models/retrain`) fine-tunes the promoted model of
   the survey's sensor kind and promotes the new version only when it is not worse on the held
   out label blocks; a new `run:phantom` job then refreshes the pre-labels (the next areas are
   the new model's doubts).
4. After each retraining the promoted version is scored on the other real sequences, which no
   model of the loop saw: point and pillar phantom P / R / F as in bench/phantom.py's
   leave-one-sequence-out tables.

The base model (0 labels) is a rotating-scanner model trained without real data
(`mmsclean train phantom --sensor rotating --out BASE.pt`, no `--semantickitti`): the state of a
team whose scanner no real label has reached yet. The bench puts it in the registry as the
promoted rotating version, as an admin's promotion would (models cannot be uploaded through the
API, by design).

    MMSCLEAN_REAL_DATA=../shared/data .venv/bin/python -m bench.labelling_loop \\
        --base-model BASE.pt [--labelled 04] [--held-out 05,08] [--steps 500,1000,2000,5000]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
from sqlmodel import Session

from app.core.sensors import SensorKind
from app.geometry.ground import estimate_ground
from app.io import open_survey
from app.io.accumulate import accumulate
from app.jobs.retraining import TRIGGER_CONFIG  # what the trigger queues
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.evaluation.reference import reference_pillar_labels, static_and_moving
from app.pipelines.phantom.model import read_card
from app.pipelines.phantom.pillars import build_pillar_map
from app.pipelines.phantom.pipeline import PhantomPipeline
from app.store.db import make_engine
from app.store.model_versions import register_version
from app.store.models import Pipeline
from app.store.pillar_labels import STORE_GRID
from app.viewer.picking import pillars_in_disc
from bench import security
from bench.common import append_results, markdown_table
from bench.phantom_quality import Tally
from tests.api.server import Server

BRUSH_RADIUS = 1.0  # metres: the viewer's default brush
JOB_TIMEOUT = 3 * 3600.0


@dataclass
class Operator:
    """The answers (reference class per pillar with points) and what was labelled so far."""

    cells: np.ndarray  # (P,) sorted store-grid ids of the pillars with points
    classes: np.ndarray  # (P,) reference PillarClass of each
    labelled: np.ndarray  # (P,) bool

    def index(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(positions in `self.cells`, found) of CELLS."""
        pos = np.clip(np.searchsorted(self.cells, cells), 0, len(self.cells) - 1)
        return pos, self.cells[pos] == cells

    def brush_stroke(self, seed_cell: int, budget: int) -> np.ndarray:
        """Positions of the unlabelled pillars with points within the brush round a pillar
        (at most `budget`, nearest first)."""
        ix, iy = STORE_GRID.decode(np.array([seed_cell], dtype=np.int64))
        centre = STORE_GRID.cell_center(ix, iy)[0]
        disc = pillars_in_disc(centre, BRUSH_RADIUS)
        pos, found = self.index(disc)
        pos, disc = pos[found], disc[found]
        keep = ~self.labelled[pos]
        pos, disc = pos[keep], disc[keep]
        dx, dy = STORE_GRID.decode(disc)
        dist = np.hypot(*(STORE_GRID.cell_center(dx, dy) - centre).T)
        return pos[np.argsort(dist, kind="stable")[:budget]]


def reference_answers(sequence: Path) -> Operator:
    """The operator's answers: the reference class of every pillar with points of the 0.2 m
    pillar map (the phantom pipeline's, on the store grid)."""
    cfg = PhantomConfig()
    amap = accumulate(open_survey(sequence, "semantickitti"), with_reference=True)
    ground = estimate_ground(amap.xyz, cfg.ground_cell, cfg.ground_opening)
    pm = build_pillar_map(amap.xyz, ground, cfg)
    classes = reference_pillar_labels(pm, *static_and_moving(amap.reference))
    centres = (pm.pillars.astype(np.float64) + 0.5) * cfg.cell_size
    cells = STORE_GRID.point_cell_ids(centres)
    order = np.argsort(cells, kind="stable")
    return Operator(cells[order], classes[order].astype(np.int64), np.zeros(len(cells), bool))


def wait_job(client: httpx.Client, job_id: int) -> dict:
    """The job once it ended (`bench.security.wait_job`); a job still going is an error here."""
    job = security.wait_job(client, job_id, JOB_TIMEOUT)
    if job["status"] in ("queued", "running"):
        raise RuntimeError(f"job {job_id} did not end within {JOB_TIMEOUT:.0f} s")
    return job


def run_phantom(client: httpx.Client, survey_id: int) -> dict:
    response = client.post("/jobs", json={"kind": "run:phantom", "survey_id": survey_id})
    response.raise_for_status()
    job = wait_job(client, response.json()["id"])
    if job["status"] != "succeeded":
        raise RuntimeError(f"run:phantom job {job['id']} {job['status']}: {job['message']}")
    return job


def label_until(client: httpx.Client, survey_id: int, operator: Operator, target: int) -> int:
    """Brush the most doubtful areas until `target` pillars are labelled; returns the strokes."""
    strokes = 0
    while operator.labelled.sum() < target:
        response = client.get(f"/surveys/{survey_id}/pillars/uncertain", params={"limit": 20})
        response.raise_for_status()
        areas = response.json()
        if not areas:
            raise RuntimeError(f"no uncertain area left after {operator.labelled.sum()} labels")
        progressed = False
        for area in areas:
            for seed in area["cell_ids"]:
                budget = target - int(operator.labelled.sum())
                if budget <= 0:
                    return strokes
                pos, found = operator.index(np.array([seed], dtype=np.int64))
                if found[0] and operator.labelled[pos[0]]:
                    continue  # an earlier stroke covered it
                stroke = operator.brush_stroke(seed, budget)
                if not len(stroke):
                    continue
                batch = [
                    {"cell_id": int(c), "label": int(k), "version": 0}
                    for c, k in zip(operator.cells[stroke], operator.classes[stroke], strict=True)
                ]
                write = client.put(f"/surveys/{survey_id}/pillars/labels", json={"labels": batch})
                write.raise_for_status()
                operator.labelled[stroke] = True
                strokes += 1
                progressed = True
        if not progressed:
            raise RuntimeError("the uncertain areas hold no unlabelled pillar with points")
    return strokes


def score(checkpoint: Path, sequences: list[Path]) -> dict[str, tuple[float, ...]]:
    """Point and pillar phantom P / R / F of a checkpoint on each held-out sequence."""
    pipeline = PhantomPipeline(PhantomConfig(), checkpoint)
    out = {}
    for sequence in sequences:
        tally = Tally()
        tally.add(pipeline.run(open_survey(sequence, "semantickitti")), with_baselines=False)
        pillar, point = tally.phantom_scores()
        out[sequence.name] = (*point, *pillar)
    return out


def promote_base(data_dir: Path, base: Path) -> None:
    """The base checkpoint as the promoted rotating phantom version (an admin's promotion)."""
    folder = data_dir / "models" / "phantom"
    folder.mkdir(parents=True, exist_ok=True)
    copy = folder / "labelling-loop-base.pt"
    shutil.copy(base, copy)
    card = read_card(base)
    copy.with_suffix(".card.json").write_text(json.dumps(card))
    engine = make_engine(f"sqlite:///{(data_dir / 'mmsclean.sqlite3').resolve()}")
    with Session(engine) as session:
        register_version(
            session, Pipeline.phantom, "labelling-loop-base", copy, {},
            {"source": str(base), "real_sequences": []}, None, True, SensorKind.ROTATING,
        )  # fmt: skip
    engine.dispose()


def promoted(client: httpx.Client) -> dict:
    versions = client.get("/models").json()
    return next(
        v for v in versions
        if v["pipeline"] == "phantom" and v["is_promoted"] and v["sensor_kind"] == "rotating"
    )  # fmt: skip


def run(args) -> tuple[str, str]:
    real = Path(os.environ["MMSCLEAN_REAL_DATA"]) / "semantickitti" / "sequences"
    held_out = [real / s.strip() for s in args.held_out.split(",") if s.strip()]
    steps = [int(s) for s in args.steps.split(",")]
    labelled_seq = real / args.labelled
    operator = reference_answers(labelled_seq)
    print(f"{args.labelled}: {len(operator.cells):,} pillars with points", flush=True)
    rows = []
    base_scores = score(Path(args.base_model), held_out)
    rows.append(["0", "", "", "", "", "", _phantom_share(args.base_model)]
                + _score_cells(base_scores, held_out))  # fmt: skip
    print(rows[-1], flush=True)
    with tempfile.TemporaryDirectory(prefix="mmsclean-labelling-") as scratch:
        data_dir = Path(scratch) / "data"
        server = Server(
            data_dir,
            env={
                "MMSCLEAN_SAMPLE_DIR": "",
                "MMSCLEAN_IMPORT_ROOT": str(real),
                "MMSCLEAN_RETRAIN_EVERY": "0",  # the bench queues the trigger's job itself
                "MMSCLEAN_WORKERS": "1",
            },
        )
        try:
            server.start(300)
            promote_base(data_dir, Path(args.base_model))
            client = server.client()
            client.timeout = 600
            response = client.post(
                "/surveys/import",
                json={"path": args.labelled, "format": "semantickitti", "name": args.labelled},
            )
            response.raise_for_status()
            survey_id = response.json()["id"]
            run_phantom(client, survey_id)
            for step in steps:
                clock = time.perf_counter()
                strokes = label_until(client, survey_id, operator, step)
                label_s = time.perf_counter() - clock
                queued = client.post(
                    "/models/retrain", json={"pipeline": "phantom", "config": TRIGGER_CONFIG}
                )
                queued.raise_for_status()
                job = wait_job(client, queued.json()["job_id"])
                current = promoted(client)
                scores = score(Path(current["checkpoint_path"]), held_out)
                if job["status"] == "succeeded":
                    result = job["result"]
                    outcome = "yes" if result["promoted"] else "no"
                    val = f"{result['validation_macro_f1']:.1f} / {result['baseline_macro_f1']:.1f}"
                else:  # what a team would see: the job's one line
                    outcome, val = f"job {job['status']}: {job['message']}", ""
                answers = np.bincount(operator.classes[operator.labelled], minlength=4)
                rows.append(
                    [f"{step:,}", " / ".join(map(str, answers)), str(strokes),
                     f"{job['seconds']:.0f}", outcome, val,
                     _phantom_share(current["checkpoint_path"])]
                    + _score_cells(scores, held_out)
                )  # fmt: skip
                print(rows[-1], f"(labelling replay {label_s:.1f} s)", flush=True)
                if step != steps[-1]:
                    run_phantom(client, survey_id)  # the next doubts are the new model's
            client.close()
            tracebacks = server.log().count("Traceback")
        finally:
            server.stop()
    header = ["labelled pillars", "ground / high / short / phantom", "brush strokes",
              "retraining s", "promoted",
              "held-out label blocks macro F new / base", "phantom prior"]  # fmt: skip
    for s in held_out:
        header += [f"{s.name} {what}" for what in ("point P", "point R", "point F", "pillar F")]
    table = markdown_table(header, rows)
    notes = (
        f"Operator: SemanticKITTI {args.labelled} (10 frames, {len(operator.cells):,} pillars "
        f"with points), uncertain-first areas from the API, brush r = {BRUSH_RADIUS:g} m, the "
        f"reference classes as answers. Base (row 0): {Path(args.base_model).name}, a "
        "rotating-scanner model trained on simulated drives only. Each retraining is the "
        "trigger's train:phantom job (default settings) on all labels so far, from the "
        "promoted version; the scores are the promoted version's after it, on sequences no "
        f"model here saw. Server tracebacks: {tracebacks}."
    )
    return table, notes


def _score_cells(scores: dict, held_out: list[Path]) -> list[str]:
    cells = []
    for s in held_out:
        p, r, f, _pp, _pr, pf = scores[s.name]
        cells += [f"{p:.1f}", f"{r:.1f}", f"{f:.1f}", f"{pf:.1f}"]
    return cells


def _phantom_share(checkpoint) -> str:
    priors = read_card(Path(checkpoint)).get("class_priors")
    return "" if priors is None else f"{100 * priors[3]:.1f} %"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base-model", required=True, help="rotating model trained on sim only")
    parser.add_argument("--labelled", default="04", help="the sequence the operator labels")
    parser.add_argument("--held-out", default="05,08", help="sequences the models are scored on")
    parser.add_argument("--steps", default="500,1000,2000,5000", help="labelled pillars")
    parser.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    args = parser.parse_args(argv)
    if "MMSCLEAN_REAL_DATA" not in os.environ:
        print("MMSCLEAN_REAL_DATA is not set: the loop needs the real SemanticKITTI sequences")
        return 2
    table, notes = run(args)
    print(table)
    print(notes)
    if not args.no_record:
        append_results(
            "Phantom: the labelling loop (labels through the API, retraining, held-out scores)",
            "python -m bench.labelling_loop " + " ".join(sys.argv[1:] if argv is None else argv),
            table,
            notes,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
