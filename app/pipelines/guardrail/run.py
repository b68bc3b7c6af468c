"""A guardrail run from survey to output folder: labels, guardrail points (LAZ), one mesh set
per guardrail (glb, obj, ply) and the report, with the paper's slice scores when the survey has
reference labels (simulator: guardrail index; SemanticKITTI: the fence class)."""

from __future__ import annotations

import datetime
import time
from pathlib import Path

import numpy as np

from app.core.sensors import SensorKind
from app.io.asprs import GUARDRAIL_ASPRS
from app.io.las import write_laz
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
from app.pipelines.guardrail.pipeline import SHIPPED, GuardrailPipeline, GuardrailResult, Progress
from app.pipelines.outputs import write_frame_labels, write_report
from app.pipelines.sensor_models import ModelChoice, choose_model


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
) -> dict:
    """`model` as a job chose it; else `model_path` forced by hand; else the shipped classifier
    of the survey's sensor kind (`sensor` declared, else detected): `sensor_models`."""
    started = time.perf_counter()
    if model is None:
        model = choose_model("guardrail", SHIPPED, survey, read_classifier_card, model_path, sensor)
    pipeline = GuardrailPipeline(config, model.path)
    result = pipeline.run(survey, progress)
    return write_guardrail_folder(survey, pipeline, result, out, started, model)


def write_guardrail_folder(
    survey: Survey,
    pipeline: GuardrailPipeline,
    result: GuardrailResult,
    out: Path,
    started: float,
    model: ModelChoice,
) -> dict:
    """The run's outputs from its result (callers that keep the result, e.g. the web app's job,
    run the pipeline themselves); `started` is the perf_counter at the start of the run."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_frame_labels(out, result.frame_labels())
    files = {}
    pts = result.stage.points
    on_rail = result.point_labels == 1
    write_laz(
        out / "guardrail_points.laz",
        pts.xyz[on_rail],
        mmsclean_label=np.ones(int(on_rail.sum()), dtype=np.uint8),
        classification=np.full(int(on_rail.sum()), GUARDRAIL_ASPRS, dtype=np.uint8),
        source_frame=pts.frame[on_rail].astype(np.uint32),
        source_index=pts.index[on_rail].astype(np.uint32),
        creation_date=datetime.date.today(),
    )
    files["guardrail_points"] = "guardrail_points.laz"
    guardrails = []
    for g in result.guardrails:
        entry: dict = {"id": g.id, "slices": int(len(g.slices)), "points": int(len(g.points))}
        if g.model is not None:
            from app.pipelines.guardrail.reconstruction import export_guardrail

            written = export_guardrail(g.model, out / "guardrails", g.id)
            entry["files"] = {k: str(Path("guardrails") / Path(v).name) for k, v in written.items()}
            entry["model"] = g.model.model
        if g.error:
            entry["error"] = g.error
        guardrails.append(entry)
    report: dict = {
        "pipeline": "guardrail",
        "survey": {"name": survey.name, "format": survey.format, "source": str(survey.source)},
        "config": pipeline.config.model_dump(),
        "model": {
            "path": str(pipeline.model_path),
            "created": pipeline.card.get("created"),
            "head": pipeline.head,
            **model.report(),
        },
        "counts": {
            "frames": len(result.frame_ids),
            "points": int(len(pts)),
            "slices": int(len(result.slice_labels)),
            "slices_with_crop": int(result.stage.has_crop.sum()),
            "guardrail_slices": int(result.slice_labels.sum()),
            "guardrail_points": int(on_rail.sum()),
            "guardrails": len(result.guardrails),
        },
        "guardrails": guardrails,
        "timings": dict(result.timings),
        "files": files,
    }
    reference = reference_points(survey, result)
    if reference is not None:
        truth, what = reference
        report["metrics"] = {"reference": what, **slice_metrics(result, truth)}
    report["timings"]["total"] = round(time.perf_counter() - started, 3)
    write_report(out, report)
    return report
