"""Guardrail jobs (the synchronous review helpers the API and the viewer call live in
`app.review.guardrails`).

- `run:guardrail`: the guardrail pipeline on the job's survey into the job's folder (the CLI's
  outputs plus `guardrail_slices.npz`, what a rebuild needs), then the slices and the
  reconstructed guardrails into the store in one transaction.
- `guardrail:rebuild`: grouping, joining and reconstruction again from the slice labels as
  people corrected them, without re-reading the survey or re-running the classifier.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from sqlmodel import Session

from app.core.bounds import RecordId
from app.core.errors import ConfigError
from app.core.settings import Settings
from app.io import open_survey
from app.jobs.cluster import log_tiles, tile_map, tile_progress
from app.jobs.memory import (
    MB,
    MemoryEstimate,
    bounded_tile_points,
    points_mb,
    survey_text,
    tile_field,
    tile_reach,
    tile_share,
)
from app.jobs.model_choice import model_for_job
from app.jobs.registry import JobContext, task
from app.jobs.task_config import refuse_model_path, validated
from app.pipelines.guardrail.classifier import read_classifier_card
from app.pipelines.guardrail.config import GuardrailConfig
from app.pipelines.guardrail.pipeline import (
    SHIPPED,
    GuardrailInstance,
    ReconstructionInput,
    StoredStage,
    rebuild_guardrails,
)
from app.pipelines.guardrail.run import STAGE_FILE, guardrail_writer, run_guardrail_report
from app.pipelines.guardrail.tiled import INDEX_CELL, TILE_LENGTH, TILE_POINTS, guardrail_halo
from app.pipelines.outputs import write_report
from app.pipelines.sensor_models import ModelChoice
from app.review.guardrails import current_run, reading_stage, stage_rows
from app.store.guardrail_review import slice_table
from app.store.guardrail_runs import (
    ModelRecord,
    SliceRows,
    replace_guardrail_models,
    replace_guardrail_run,
)
from app.store.models import GuardrailKind, ModelVersion, Pipeline, Survey
from app.store.surveys import get_survey, survey_footprint

REBUILD_FIELDS = ("min_guardrail_length", "join_gap", "join_lateral", "ground_clearance")
# points, road / component / slice labels, crops' features: 263 bytes per point measured on the
# fullest window of `guardrail.tiled.TILE_POINTS`, with a margin
GUARDRAIL_BYTES_PER_POINT = 300.0
# held once the tiles are done: every slice's row (about 100 bytes, 350 slices per million points
# of a simulated urban street) and the guardrail being built (at most the guardrails' points,
# 0.6 % of the survey's there, 64 bytes each): 0.4 bytes per survey point, taken generously for
# rail-lined roads (the classifier inputs and the slices' points stay in the tiles' files)
GATHERED_BYTES_PER_POINT = 1.0


# --- configuration ------------------------------------------------------------------------


class GuardrailJobOptions(BaseModel):
    """What a run:guardrail job sets beside the pipeline's parameters (GuardrailConfig's)."""

    model_config = ConfigDict(protected_namespaces=())

    model_id: RecordId | None = Field(
        None, description="classifier version to run (GET /models); default: the promoted one"
    )
    tile_length: float = Field(
        TILE_LENGTH, ge=20.0, le=1000.0, description="metres of trajectory per tile"
    )


def guardrail_options(
    config: dict[str, Any], settings: Settings | None = None
) -> tuple[GuardrailConfig, GuardrailJobOptions]:
    """`run:guardrail`'s config: GuardrailConfig fields plus `model_id` and `tile_length`."""
    values = dict(config or {})
    refuse_model_path(values)
    own = {k: values.pop(k) for k in GuardrailJobOptions.model_fields if k in values}
    option = validated(GuardrailJobOptions, own)
    known = (*GuardrailConfig.model_fields, *GuardrailJobOptions.model_fields)
    cfg = validated(GuardrailConfig, values, known=known)
    return cfg, option


def classifier_for_job(
    session: Session, survey: Survey, model_id: int | None
) -> tuple[ModelVersion, ModelChoice]:
    """The classifier version to run on SURVEY and why (`model_choice.model_for_job`)."""
    return model_for_job(
        session, Pipeline.guardrail, survey, model_id, SHIPPED, read_classifier_card
    )


def _survey_id(context: JobContext) -> int:
    if context.survey_id is None:
        raise ConfigError("survey_id", "guardrail jobs need a survey")
    return context.survey_id


# --- run ----------------------------------------------------------------------------------


def _json_safe(value: Any) -> Any:
    """JSON columns and API answers refuse NaN / inf and numpy types: None / plain values."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def model_records(
    saved: ReconstructionInput, guardrails: list[GuardrailInstance], config: GuardrailConfig
) -> list[ModelRecord]:
    """Store records of the guardrails that were reconstructed as a pipe or a beam (others,
    with fewer than two poles or a failed reconstruction, stay in the report only)."""
    s = saved.slices
    out = []
    for g in guardrails:
        written = g.files
        if g.model is None or written is None or g.model.kind not in ("pipe", "beam"):
            continue
        model = g.model.model
        station = s.station[g.slices]
        keys = np.stack([s.component[g.slices], s.station_index[g.slices]], axis=1)
        params = _json_safe(
            {
                **model,
                "files": {k: str(Path(v).resolve()) for k, v in written.items()},
                "guardrail_id": g.id,
                "points": int(len(g.points)),
                "station_m": [float(station.min()), float(station.max())],
                "ground_clearance": config.ground_clearance,
            }
        )
        out.append(
            ModelRecord(
                kind=GuardrailKind(g.model.kind),
                mesh_path=params["files"]["glb"],
                params=params,
                unit_count=int(model.get("units") or 0),
                icp_residual=params.get("icp_residual"),
                slices=list(zip(keys[:, 0].tolist(), keys[:, 1].tolist(), strict=True)),
            )
        )
    return out


def check_run_config(config: dict[str, Any], settings: Settings) -> None:
    """Refuse a bad `run:guardrail` config when the job is queued (422), not in the worker."""
    guardrail_options(config, settings)


def estimate_run(session: Session, survey: int | None, config: dict[str, Any]) -> MemoryEstimate:
    """run:guardrail's memory: one tile's points with their slice and component arrays (tiles
    run one at a time per worker; a tile holds its share of the survey's points by trajectory
    length, the length taken as the trajectory's bounding-box diagonal, so the share comes out
    generous), and what the job holds once the tiles are done: every slice's row and one
    guardrail's points at a time (the classifier inputs and the slices' points stay in the
    tiles' files)."""
    cfg, option = guardrail_options(config)
    if survey is None:
        return MemoryEstimate("no survey")
    footprint = survey_footprint(session, survey)
    halo = guardrail_halo(cfg.with_correction({}))
    reach = tile_reach(option.tile_length, halo)
    share = tile_share(footprint, reach)
    tile_points = bounded_tile_points(footprint, reach, halo, INDEX_CELL, TILE_POINTS)
    estimate = MemoryEstimate(survey_text(footprint))
    estimate.add(
        tile_field(footprint, option.tile_length),
        tile_points * GUARDRAIL_BYTES_PER_POINT / MB,
        f"{GUARDRAIL_BYTES_PER_POINT:.0f} bytes per point of a {reach:.0f} m tile "
        f"({share:.0%} of the survey, at most {TILE_POINTS:,} points)",
    )
    return estimate.add(
        "survey_id",
        points_mb(footprint, GATHERED_BYTES_PER_POINT),
        f"every slice's row and the guardrail being built, about "
        f"{GATHERED_BYTES_PER_POINT:.0f} byte per point of the survey",
    )


def check_rebuild_config(config: dict[str, Any], settings: Settings) -> None:
    validated(GuardrailConfig, config, known=REBUILD_FIELDS)


@task("run:guardrail", check=check_run_config, model="guardrail", estimate=estimate_run)
def run_guardrail(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """The pipeline on the job's survey tile by tile (on the server's tile cluster), its
    contract files and the review's slice stage in the workdir, then the slices and the
    reconstructed guardrails into the store in one transaction. A resumed job keeps the tiles
    its earlier attempt finished."""
    cfg, option = guardrail_options(config, context.settings)
    survey_id = _survey_id(context)
    with Session(context.engine) as session:
        record = get_survey(session, survey_id)
        source, fmt = record.source_path, record.format
        _, choice = classifier_for_job(session, record, option.model_id)
    if choice.off_domain:
        context.log.warning("%s", choice.report()["warning"])
    survey = open_survey(source, fmt)
    out = context.workdir
    done = run_guardrail_report(
        survey, out, cfg, model=choice, progress=tile_progress(context),
        tile_length=option.tile_length, map_tiles=tile_map(context.settings), keep_stage=True,
    )  # fmt: skip
    report, run = done.report, done.run
    log_tiles(context, report["tiles"])
    models = []
    if run.rails is not None:
        models = model_records(run.rails.index, done.guardrails, done.pipeline.config)
    s = run.slices
    rows = SliceRows(
        component=s.component,
        slice_index=s.slice_index,
        station=s.station,
        predicted=s.raw.astype(np.int64),
        probability=s.probability,
        corrected=s.corrected.astype(np.int64),
    )
    context.progress(0.95, "storing slices and models")
    stage_path = out / STAGE_FILE
    with Session(context.engine) as session:
        stored = replace_guardrail_run(
            session, survey_id, rows, models, stage_path=str(stage_path),
            config=done.pipeline.config.model_dump(), job_id=context.job_id,
            user_id=context.user_id,
        )  # fmt: skip
    context.progress(1.0, f"{stored['slices']} slices, {stored['models']} guardrail models")
    output = {
        "slice_stage": str(stage_path),
        "report": str(out / "report.json"),
        **{name: str(out / path) for name, path in report["files"].items()},
    }
    for g in done.guardrails:
        for fmt_name, path in (g.files or {}).items():
            output[f"{g.id}.{fmt_name}"] = str(Path(path).resolve())
    return {
        "files": output,
        "report": output["report"],
        "counts": {**report["counts"], **stored},
        "metrics": report.get("metrics"),
    }


# --- rebuild ------------------------------------------------------------------------------


@task("guardrail:rebuild", check=check_rebuild_config)
def rebuild_guardrail_models(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    survey_id = _survey_id(context)
    validated(GuardrailConfig, config, known=REBUILD_FIELDS)
    with Session(context.engine) as session:
        run = current_run(session, survey_id)
        table = slice_table(session, survey_id)
    context.progress(0.02, "loading the slice stage")
    with reading_stage(run) as path:  # each guardrail's points read for it alone, then written
        stage = StoredStage.open(path)
        slices = stage.index
        at = stage_rows(slices, table.component, table.slice_index)
        labels = np.zeros(len(slices.slices), dtype=bool)
        labels[at] = table.label.astype(bool)
        cfg = validated(
            GuardrailConfig,
            {**slices.config.model_dump(), **(config or {})},
            known=tuple(GuardrailConfig.model_fields),
        )
        guardrails = rebuild_guardrails(
            stage, labels, cfg, lambda step, f: context.progress(0.05 + 0.85 * f, step),
            guardrail_writer(context.workdir), tile_map(context.settings),
        )  # fmt: skip
    models = model_records(slices, guardrails, cfg)
    context.progress(0.95, "storing models")
    with Session(context.engine) as session:
        stored = replace_guardrail_models(
            session, survey_id, run, models, job_id=context.job_id, user_id=context.user_id
        )
    counts = {
        "slices": int(len(labels)),
        "guardrail_slices": int(labels.sum()),
        "guardrails": len(guardrails),
        **stored,
    }
    report = {
        "pipeline": "guardrail",
        "step": "rebuild",
        "run_job_id": run.job_id,
        "config": cfg.model_dump(),
        "counts": counts,
        "guardrails": [
            {
                "id": g.id,
                "slices": int(len(g.slices)),
                "points": int(len(g.points)),
                **({"error": g.error} if g.error else {}),
            }
            for g in guardrails
        ],  # fmt: skip
    }
    report_path = write_report(context.workdir, report)
    output = {"report": str(report_path)}
    for g in guardrails:
        for fmt_name, path in (g.files or {}).items():
            output[f"{g.id}.{fmt_name}"] = str(path)
    context.progress(1.0, f"{stored['models']} guardrail models ({stored['kept']} kept)")
    return {"files": output, "report": str(report_path), "counts": counts}
