"""A guardrail run from survey to output folder: labels, guardrail points (LAZ), one mesh set
per guardrail (glb, obj, ply) and the report, with the paper's slice scores when the survey has
reference labels (simulator: guardrail index; SemanticKITTI: the fence class)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.core.sensors import SensorKind
from app.io.survey import Survey
from app.metrics.classification import binary_scores
from app.pipelines.guardrail.classifier import read_classifier_card
from app.pipelines.guardrail.config import GuardrailConfig
from app.pipelines.guardrail.evaluation.reference import (
    DESCRIPTIONS,
    guardrail_truth,
    point_reference,
    reference_kind,
    slice_truth,
)
from app.pipelines.guardrail.pipeline import (
    SHIPPED,
    GuardrailInstance,
    GuardrailPipeline,
    GuardrailResult,
    Progress,
    rebuild_guardrails,
)
from app.pipelines.guardrail.tile_assembly import slice_metrics_from_counts
from app.pipelines.guardrail.tiled import TILE_LENGTH, GuardrailTiledRun, run_guardrail_tiled
from app.pipelines.outputs import write_report
from app.pipelines.sensor_models import ModelChoice, choose_model
from app.pipelines.tiling import TileMap, in_process, tiles_report

STAGE_FILE = "guardrail_slices.npz"  # every slice with its points: what a rebuild needs
FEATURES_FILE = "slice_features.npz"  # classifier inputs per slice: what retraining reads


def reference_points(survey: Survey, result: GuardrailResult) -> tuple[np.ndarray, str] | None:
    """Per point of the run: True on a guardrail (simulator) or a fence (SemanticKITTI)."""
    kind = reference_kind(survey.reference_label_kinds)
    if kind is None:
        return None
    values = point_reference(survey, result.stage.points, kind)
    return guardrail_truth(kind, values), DESCRIPTIONS[kind]


def slice_metrics(result: GuardrailResult, truth_points: np.ndarray) -> dict:
    """The paper's Table 2 (slice precision / recall / F), before and after correction, and the
    point-level scores."""
    truth = slice_truth(result.stage, np.where(truth_points, 0, -1)).astype(bool)
    return {
        "slices": int(len(truth)),
        "reference_guardrail_slices": int(truth.sum()),
        "slice_raw": binary_scores(truth, result.raw_labels).as_dict(),
        "slice": binary_scores(truth, result.slice_labels).as_dict(),
        "point": binary_scores(truth_points, result.point_labels == 1).as_dict(),
    }


def run_guardrail_to_folder(
    survey: Survey,
    out: Path,
    config: GuardrailConfig | None = None,
    model_path: Path | None = None,
    progress: Progress | None = None,
    sensor: SensorKind | None = None,
    model: ModelChoice | None = None,
    tile_length: float = TILE_LENGTH,
    map_tiles: TileMap = in_process,
) -> dict:
    """`run_guardrail_report`'s report."""
    return run_guardrail_report(
        survey, out, config, model_path, progress, sensor, model, tile_length, map_tiles
    ).report


@dataclass
class GuardrailRun:
    """A run's report with what the web app's store keeps of it."""

    report: dict
    pipeline: GuardrailPipeline
    run: GuardrailTiledRun
    guardrails: list[GuardrailInstance]  # their slices index `run.rails.index`, files under out


def run_guardrail_report(
    survey: Survey,
    out: Path,
    config: GuardrailConfig | None = None,
    model_path: Path | None = None,
    progress: Progress | None = None,
    sensor: SensorKind | None = None,
    model: ModelChoice | None = None,
    tile_length: float = TILE_LENGTH,
    map_tiles: TileMap = in_process,
    keep_stage: bool = False,
) -> GuardrailRun:
    """The survey tile by tile (`tiled`) into `out`: labels, guardrail points, then the
    guardrails grouped over the whole survey and reconstructed, their meshes and the report.
    `model` as a job chose it; else `model_path` forced by hand; else the shipped classifier
    of the survey's sensor kind (`sensor` declared, else detected): `sensor_models`. Tiles an
    earlier attempt in `out` finished are kept; `map_tiles` may spread them over a cluster.
    `keep_stage`: also `STAGE_FILE` and `FEATURES_FILE` (every slice: the web app's review)."""
    started = time.perf_counter()
    out = Path(out).resolve()  # the guardrails are written there by the cluster's workers too
    if model is None:
        model = choose_model("guardrail", SHIPPED, survey, read_classifier_card, model_path, sensor)
    pipeline = GuardrailPipeline(config, model.path)
    cfg = pipeline.config
    run = run_guardrail_tiled(
        pipeline, survey, out, tile_length, progress=progress, map_tiles=map_tiles,
        keep_stage=keep_stage, stage_path=out / STAGE_FILE, features_path=out / FEATURES_FILE,
    )  # fmt: skip
    guardrails: list[GuardrailInstance] = []
    clock = time.perf_counter()
    if run.rails is not None:
        every = np.ones(len(run.rails.index.slices), dtype=bool)  # `rails` are guardrail slices
        guardrails = rebuild_guardrails(  # each read, rebuilt, written and let go
            run.rails, every, cfg, _reconstruction(progress), guardrail_writer(out), map_tiles
        )
    timings = {**run.timings, "reconstruction": round(time.perf_counter() - clock, 3)}
    entries = []
    for g in guardrails:
        entry: dict = {"id": g.id, "slices": int(len(g.slices)), "points": int(len(g.points))}
        if g.files is not None:
            entry["files"] = {k: str(Path(v).relative_to(out)) for k, v in g.files.items()}
            entry["model"] = g.model.model  # type: ignore[union-attr]
        if g.error:
            entry["error"] = g.error
        entries.append(entry)
    report: dict = {
        "pipeline": "guardrail",
        "survey": {"name": survey.name, "format": survey.format, "source": str(survey.source)},
        "config": cfg.model_dump(),
        "model": {
            "path": str(pipeline.model_path),
            "created": pipeline.card.get("created"),
            "head": pipeline.head,
            **model.report(),
        },
        "tiles": tiles_report(run.index.layout, run.tiles_run, run.worker_peak_mb),
        "counts": {"frames": len(survey.frames), **run.counts, "guardrails": len(guardrails)},
        "guardrails": entries,
        "timings": timings,
        "files": {**run.files},
    }
    if run.metric_counts is not None:
        kind = reference_kind(survey.reference_label_kinds)
        report["metrics"] = {
            "reference": DESCRIPTIONS[kind] if kind else None,
            **slice_metrics_from_counts(run.metric_counts, int(run.counts["slices"])),
        }
    report["timings"]["total"] = round(time.perf_counter() - started, 3)
    write_report(out, report)
    return GuardrailRun(report, pipeline, run, guardrails)


def _reconstruction(progress: Progress | None) -> Progress:
    """The reconstruction's progress, after the tiles' (which end at 1)."""
    return lambda stage, fraction: progress(stage, 1.0) if progress is not None else None


def guardrail_writer(out: Path) -> Callable[[GuardrailInstance], dict[str, str]]:
    """`rebuild_guardrails`' `write`: a reconstructed guardrail's meshes under OUT/guardrails/."""
    from app.pipelines.guardrail.reconstruction import export_guardrail

    return lambda g: export_guardrail(g.model, Path(out) / "guardrails", g.id)  # type: ignore[arg-type]
