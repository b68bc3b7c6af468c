"""`run:phantom`: the phantom pipeline on a stored survey, its output folder in the job's
workdir, and the CNN's pillar classes stored as model pre-labels for the labelling view.

Pre-labels go onto the store's one world grid (`STORE_GRID`), so they line up with human labels
of any earlier or later run. A survey keeps only its newest model labels: the old ones are
replaced in the same transaction that writes the new, so a reader never sees half of each.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from sqlmodel import Session

from app.core.bounds import RecordId
from app.core.errors import ConfigError
from app.core.settings import Settings
from app.io import open_survey
from app.jobs.cluster import log_tiles, shared_threads, tile_map, tile_progress
from app.jobs.memory import (
    MB,
    MemoryEstimate,
    bounded_tile_points,
    survey_text,
    tile_field,
    tile_reach,
    tile_share,
)
from app.jobs.model_choice import model_for_job
from app.jobs.registry import JobContext, task
from app.jobs.task_config import validated
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.model import SHIPPED, read_card
from app.pipelines.phantom.run import run_phantom_to_folder
from app.pipelines.phantom.tiled import INDEX_CELL, TILE_LENGTH, TILE_POINTS, phantom_halo
from app.pipelines.sensor_models import ModelChoice
from app.store.model_labels import store_model_labels
from app.store.models import ModelVersion, Pipeline, Survey
from app.store.pillar_labels import STORE_GRID
from app.store.surveys import get_survey, survey_footprint

KIND = "run:phantom"
# overall progress at the start and end of the tiles; the rest is assembling and ingestion
INGEST_AT = 0.9
PHANTOM_BYTES_PER_POINT = 200.0  # map xyz, ground, pillar keys, sort buffers, labels


class PhantomJobConfig(BaseModel):
    """What a run:phantom job may set; the pipeline parameters stay the paper's."""

    model_config = ConfigDict(extra="forbid", protected_namespaces=())

    model_id: RecordId | None = Field(
        None, description="phantom model version to run (GET /models); default: the promoted one"
    )
    dense: bool = True  # dense tiled inference (False: the paper's per-window path)
    refine: bool = True  # Algorithm 1 neighbourhood vote
    tile_length: float = Field(
        TILE_LENGTH, ge=20.0, le=1000.0, description="metres of trajectory per tile"
    )


def parse_config(config: dict[str, Any], settings: Settings | None = None) -> PhantomJobConfig:
    return validated(PhantomJobConfig, config)


def check_config(config: dict[str, Any], settings: Settings) -> None:
    parse_config(config, settings)


def estimate_memory(session: Session, survey: int | None, config: dict[str, Any]) -> MemoryEstimate:
    """run:phantom's memory: one tile's accumulated map and pillar arrays (tiles run one at a
    time per worker). A tile holds its share of the survey's points by trajectory length: the
    length is taken as the trajectory's bounding-box diagonal, shorter than a winding drive, so
    the share comes out generous."""
    if survey is None:
        return MemoryEstimate("no survey")
    footprint = survey_footprint(session, survey)
    tile_length = parse_config(config).tile_length
    halo = phantom_halo(PhantomConfig())
    reach = tile_reach(tile_length, halo)
    share = tile_share(footprint, reach)
    tile_points = bounded_tile_points(footprint, reach, halo, INDEX_CELL, TILE_POINTS)
    return MemoryEstimate(survey_text(footprint)).add(
        tile_field(footprint, tile_length),
        tile_points * PHANTOM_BYTES_PER_POINT / MB,
        f"{PHANTOM_BYTES_PER_POINT:.0f} bytes per point of a {reach:.0f} m tile "
        f"({share:.0%} of the survey, at most {TILE_POINTS:,} points)",
    )


def model_version_for(
    session: Session, survey: Survey, model_id: int | None
) -> tuple[ModelVersion, ModelChoice]:
    """The version row of the checkpoint to run and why (`model_choice.model_for_job`)."""
    return model_for_job(session, Pipeline.phantom, survey, model_id, SHIPPED, read_card)


def model_label_rows(pillars_npz: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(cell ids on STORE_GRID, argmax class, max posterior) of the pillars the CNN judged; one
    row per store cell (the most confident pillar, should the run's grid be finer)."""
    with np.load(pillars_npz) as data:
        classified = data["classified"].astype(bool)
        pillars = data["pillars"][classified]
        probabilities = data["probabilities"][classified]
        cell_size = float(data["cell_size"])
    centres = (pillars.astype(np.float64) + 0.5) * cell_size  # world x, y of pillar centres
    cells = STORE_GRID.point_cell_ids(centres)
    labels = probabilities.argmax(axis=1).astype(np.int64)
    confidence = np.clip(probabilities.max(axis=1).astype(np.float64), 0.0, 1.0)
    order = np.lexsort((-confidence, cells))
    cells, labels, confidence = cells[order], labels[order], confidence[order]
    first = np.ones(len(cells), dtype=bool)
    first[1:] = cells[1:] != cells[:-1]
    return cells[first], labels[first], confidence[first]


@task(KIND, check=check_config, model="phantom", estimate=estimate_memory)
def run_phantom(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    options = parse_config(config, context.settings)
    if context.survey_id is None:
        raise ConfigError("survey_id", f"{KIND} jobs need a survey")
    with Session(context.engine, expire_on_commit=False) as session:
        record = get_survey(session, context.survey_id)
        source, fmt = record.source_path, record.format
        version, choice = model_version_for(session, record, options.model_id)
    checkpoint = choice.path
    context.log.info("survey %s (%s, %s), model %s", context.survey_id, fmt, source, checkpoint)
    context.progress(0.0, "opening the survey")
    survey = open_survey(source, fmt)
    threads = shared_threads(context.settings)
    if choice.off_domain:
        context.log.warning("%s", choice.report()["warning"])
    report = run_phantom_to_folder(
        survey,
        context.workdir,
        PhantomConfig(threads=threads),
        dense=options.dense,
        refine=options.refine,
        progress=tile_progress(context),
        model=choice,
        tile_length=options.tile_length,
        map_tiles=tile_map(context.settings),
    )
    log_tiles(context, report["tiles"])
    context.progress(INGEST_AT, "storing model pre-labels")  # last chance to cancel
    cells, labels, confidence = model_label_rows(context.workdir / report["files"]["pillars"])
    written = store_model_labels(
        context.engine,
        context.survey_id,
        cells,
        labels,
        confidence,
        version.id,
        context.user_id,
        context.job_id,
    )
    context.log.info("stored %d model pre-labels (model version %d)", written, version.id)
    files = {name: str(context.workdir / rel) for name, rel in report["files"].items()}
    files["labels"] = str(context.workdir / "labels")
    files["report"] = str(context.workdir / "report.json")
    result: dict[str, Any] = {
        "files": files,
        "report": files["report"],
        "counts": {**report["counts"], "model_labels": written},
        "model_version_id": version.id,
        "model": report["model"],
        "timings": report["timings"],
    }
    if "metrics" in report:
        result["metrics"] = report["metrics"]
    return result
