"""Clutter jobs of the web app: `run:clutter` runs the pipeline, writes the command-line
contract's files and puts everything it removed up for review; `clutter:recompute` rebuilds the
cleaned and removed maps from the reviewers' decisions.

The review units ("instances"), their membership files and mask images are made by
`app.pipelines.clutter.review_units`.
The mask images lie in the run's folder: recompute finds the membership of the instances in
the store from their `mask_path`, so the rows and the files cannot come from different runs.
Reviewers' corrections of the membership apply first (`app.store.clutter_corrections`: points
taken out of an instance are kept, a missed object added is a new instance); then a decision
applies to all points of its instance: approved -> removed, rejected -> kept, pending -> the
pipeline's flag.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from sqlmodel import Session

from app.core.errors import ConfigError, ConflictError, InputError
from app.core.settings import Settings
from app.io import open_survey
from app.io.survey import Survey
from app.jobs.cluster import log_tiles, shared_threads, tile_map, tile_progress
from app.jobs.memory import (
    MEAN_RAY_M,
    SENSOR_REACH_M,
    MemoryEstimate,
    dufomap_mb,
    extent_text,
    frame_grid_mb,
    points_mb,
    survey_text,
    tile_field,
    tile_reach,
    tile_share,
)
from app.jobs.registry import JobContext, task
from app.jobs.task_config import validated
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.maps import maps_offset, write_frame_maps
from app.pipelines.clutter.review_corrections import ADD, REMOVE
from app.pipelines.clutter.review_units import apply_decisions
from app.pipelines.clutter.run import reference_metrics, run_clutter_report
from app.pipelines.clutter.segmenter import WEIGHTS_FILE
from app.pipelines.clutter.tiled import TILE_LENGTH, clutter_halo
from app.pipelines.outputs import write_frame_labels, write_report
from app.pipelines.tiling import MAPS
from app.store import clutter_corrections, clutter_review
from app.store.models import Decision
from app.store.surveys import get_survey, survey_footprint

# per point a tile reads: its evidence, maps and review units (`python -m bench.clutter_memory`:
# a worker's peak grows by about 50 bytes per point read on a simulated profile survey, the
# free-space map included; SemanticKITTI 04's ten frames took 308 MB in all without the camera)
CLUTTER_BYTES_PER_POINT = 80.0
SEGMENTER_MB = 800.0  # ESPNetv2 and torch's buffers (measured: 755 MB more on SemanticKITTI 04)
# a reviewer's decision as the review units' verdict: removed, kept, the pipeline's flag
VERDICT = {Decision.approved: 1, Decision.rejected: 0, Decision.pending: -1}


# --- run:clutter --------------------------------------------------------------------------

SEGMENTATION_UPSTREAM = (
    "GitHub sacmehta/EdgeNets, model/segmentation/model_zoo/espnetv2/" + WEIGHTS_FILE
)


def segmentation_weights(settings: Settings) -> tuple[bool, Path]:
    """(whether the camera masks' ESPNetv2 weights are on this server, where they belong): the
    dashboard unticks the camera option and says where to get them when they are not."""
    path = settings.weights_dir / WEIGHTS_FILE
    return path.is_file(), path


def check_run_config(config: dict[str, Any], settings: Settings) -> None:
    """Refuse a bad `run:clutter` config when the job is queued (422), not in the worker."""
    clutter_job_config(config)


def estimate_run(session: Session, survey: int | None, config: dict[str, Any]) -> MemoryEstimate:
    """run:clutter's memory per tile worker: its frames' point arrays, a frame's ground grid,
    the segmentation network, DUFOMap's octree over the tile's rays (measured peak on
    SemanticKITTI 04, 1,234,476 points in one tile, defaults: 1,060 MB; this estimate: about
    1,600 MB). A tile reads its share of the survey's frames by trajectory length: the length
    is taken as the trajectory's bounding-box diagonal, shorter than a winding drive, so the
    share comes out generous."""
    cfg, tile_length = clutter_job_config(config)
    if survey is None:
        return MemoryEstimate("no survey")
    footprint = survey_footprint(session, survey)
    reach_m = tile_reach(tile_length, clutter_halo(cfg))
    share = tile_share(footprint, reach_m)
    field = tile_field(footprint, tile_length)
    reach = 2 * SENSOR_REACH_M
    estimate = MemoryEstimate(survey_text(footprint))
    estimate.add(
        field,
        points_mb(footprint, CLUTTER_BYTES_PER_POINT * share),
        f"{CLUTTER_BYTES_PER_POINT:.0f} bytes per point of a {reach_m:.0f} m tile "
        f"({share:.0%} of the survey)",
    )
    estimate.add(
        "config.ground_cell",
        frame_grid_mb(cfg.ground_cell),
        f"{cfg.ground_cell:g} m ground cells over a frame's {reach:.0f} x {reach:.0f} m",
    )
    if cfg.use_camera:
        estimate.add("config.use_camera", SEGMENTER_MB, "the segmentation network")
    if cfg.use_free_space:
        estimate.add(
            "config.dufomap_resolution",
            dufomap_mb(footprint, cfg.dufomap_resolution) * share,
            f"{cfg.dufomap_resolution:g} m free-space voxels over a tile's share of "
            f"{extent_text(footprint)}, rays of about {MEAN_RAY_M:.0f} m",
        )
    return estimate


def check_recompute_config(config: dict[str, Any], settings: Settings) -> None:
    if config:
        raise ConfigError(f"config.{next(iter(config))}", "clutter:recompute takes no options")


@task(clutter_review.RUN_KIND, check=check_run_config, estimate=estimate_run)
def run_clutter_task(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """The pipeline on the job's survey tile by tile (on the server's tile cluster), its
    contract files in the workdir, and its instances (each pending) in the store in place of
    the previous run's. A resumed job keeps the tiles its earlier attempt finished."""
    cfg, tile_length = clutter_job_config(config)
    if cfg.threads == 0:  # the tile workers share the cores
        cfg = cfg.model_copy(update={"threads": shared_threads(context.settings)})
    survey = _open_survey(context)
    report, run = run_clutter_report(
        survey, context.workdir, cfg, progress=tile_progress(context), tile_length=tile_length,
        map_tiles=tile_map(context.settings), review=True,
        cache_dir=context.settings.cache_dir / "segmentation",
        weights_dir=context.settings.weights_dir,
    )  # fmt: skip
    log_tiles(context, report["tiles"])
    context.progress(0.9, "instances for review")  # last chance to cancel
    out = context.workdir
    rows = run.rows
    with Session(context.engine) as session:
        clutter_review.replace_instances(
            session, survey_id(context), rows, context.user_id, context.job_id
        )
    classes: dict[str, int] = {}
    for row in rows:
        classes[row["class_name"]] = classes.get(row["class_name"], 0) + 1
    counts = {**report["counts"], "instances": len(rows), "instances_per_class": classes}
    report["counts"] = counts
    report_path = write_report(out, report)
    context.progress(1.0, f"{len(rows)} instances to review")
    files = {name: str((out / path).resolve()) for name, path in report["files"].items()}
    files["labels"] = str((out / "labels").resolve())
    files["instances"] = str((out / "instances").resolve())
    files["report"] = str(report_path.resolve())
    return {
        "files": files,
        "report": files["report"],
        "counts": counts,
        "metrics": report.get("metrics"),
    }


def clutter_job_config(config: dict[str, Any]) -> tuple[ClutterConfig, float]:
    """The job config as a ClutterConfig and the tile length; an unknown key or a bad value
    names the field."""
    values = dict(config or {})
    tiles = validated(ClutterTiles, {"tile_length": values.pop("tile_length", TILE_LENGTH)})
    return clutter_config(values), tiles.tile_length


class ClutterTiles(BaseModel):
    """How a run:clutter job cuts the survey (the pipeline's parameters are ClutterConfig's)."""

    model_config = ConfigDict(extra="forbid")

    tile_length: float = Field(
        TILE_LENGTH, ge=20.0, le=1000.0, description="metres of trajectory per tile"
    )


def clutter_config(config: dict[str, Any]) -> ClutterConfig:
    """The pipeline parameters as a ClutterConfig; an unknown key or a bad value names the
    field."""
    return validated(ClutterConfig, config, known=tuple(ClutterConfig.model_fields))


def survey_id(context: JobContext) -> int:
    if context.survey_id is None:
        raise ConfigError("survey_id", "a clutter job needs a survey")
    return context.survey_id


def _open_survey(context: JobContext) -> Survey:
    with Session(context.engine) as session:
        record = get_survey(session, survey_id(context))
        source, fmt = record.source_path, record.format
    return open_survey(Path(source), fmt)


# --- clutter:recompute --------------------------------------------------------------------


@task(clutter_review.RECOMPUTE_KIND, check=check_recompute_config)
def recompute_clutter(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """The cleaned and removed maps (and labels) of the survey from the reviewers' decisions
    on the instances of its current clutter run."""
    check_recompute_config(config, context.settings)
    started = time.perf_counter()
    sid = survey_id(context)
    with Session(context.engine) as session:
        record = get_survey(session, sid)
        source, fmt = record.source_path, record.format
        decisions = clutter_review.review_decisions(session, sid)
        corrections = clutter_corrections.survey_corrections(session, sid)
        run = clutter_review.run_folder_of([d[3] for d in decisions])
        if run is None:
            job = clutter_review.latest_run(session, sid)
            if job is None or "instances" not in job.result.get("files", {}):
                raise ConflictError(f"survey {sid} has no clutter run to review; run clutter")
            run = Path(job.result["files"]["instances"]).parent
    survey = open_survey(Path(source), fmt)
    run_config = _run_config(run)
    context.progress(0.05, "applying the decisions")
    verdicts = [(frame_id, index, VERDICT[d]) for frame_id, index, d, _ in decisions]
    removed, in_view, pipeline_removed = apply_decisions(
        survey, run / "instances", verdicts, corrections
    )
    context.progress(0.4, "writing the maps")
    out = context.workdir
    write_frame_labels(
        out, {f.frame_id: r.astype(np.uint8) for f, r in zip(survey.frames, removed, strict=True)}
    )
    frames = np.arange(len(survey.frames))
    offset = maps_offset(survey)
    maps = write_frame_maps(out, "", survey, frames, removed, run_config.voxel_dedup, offset)
    files = {kind: str((out / maps[kind]).resolve()) for kind in MAPS}
    tally = {d.value: 0 for d in Decision}
    for _, _, decision, _ in decisions:
        tally[decision.value] += 1
    counts = {
        "frames": len(removed),
        "points": int(sum(len(r) for r in removed)),
        "removed_points": int(sum(int(r.sum()) for r in removed)),
        "pipeline_removed_points": pipeline_removed,
        "map_points": maps["map_points"],
        "instances": len(decisions),
        "decisions": tally,
        "corrections": {
            kind: sum(c.kind == kind for cs in corrections.values() for c in cs)
            for kind in (REMOVE, ADD)
        },
    }
    report: dict[str, Any] = {
        "pipeline": "clutter",
        "recomputed_from": str(run),
        "survey": {"name": survey.name, "format": survey.format, "source": str(survey.source)},
        "config": run_config.model_dump(),
        "counts": counts,
        "files": {name: Path(path).name for name, path in files.items()},
    }
    metrics = reference_metrics(survey, removed, in_view)
    if metrics is not None:
        report["metrics"] = metrics
    report["timings"] = {"total": round(time.perf_counter() - started, 3)}
    report_path = write_report(out, report)
    context.progress(1.0, f"{counts['removed_points']} points removed after review")
    files["labels"] = str((out / "labels").resolve())
    files["report"] = str(report_path.resolve())
    return {"files": files, "report": files["report"], "counts": counts, "metrics": metrics}


def _run_config(run: Path) -> ClutterConfig:
    path = run / "report.json"
    try:
        return ClutterConfig.model_validate(json.loads(path.read_text())["config"])
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(path, f"is not the report of a clutter run ({exc})") from None
