"""`import:survey`: register a survey from a server path as a job, for drives whose opening takes
long (a KITTI raw drive without OXTS gets its poses from LiDAR odometry first: 1.6 s for the
20-frame sample drive, uncached). The import route of the API does the same in the request;
both go through `app.review.surveys.import_source`. Config: `path` (inside the import root),
optional `format`, `name` and `sensor` (rotating / profile; detected when absent); result: the
new survey's id and name.

`prepare:viewer`: the survey's map for the viewer (`review/survey_map.py`), built when a survey of
5 M points or more is imported (the API's route and `import:survey` queue it) so that its first
scene opens at once, not after the minute a survey of tens of millions of points takes to build;
also queued by hand through /jobs. No options; result: points, tiles and overview points of the
map.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlmodel import Session

from app.core.errors import ConfigError
from app.core.sensors import SensorKind, parse_sensor_kind
from app.core.settings import Settings
from app.io.import_root import resolve_import_path
from app.jobs.memory import MemoryEstimate, points_mb, survey_text
from app.jobs.queue import enqueue
from app.jobs.registry import JobContext, task
from app.review.survey_map import MapSource, load_map
from app.review.surveys import import_source
from app.store.models import Survey
from app.store.surveys import get_survey, survey_footprint

KIND = "import:survey"
FIELDS = ("path", "format", "name", "sensor")
PREPARE_VIEWER = "prepare:viewer"
# what building the viewer's map holds besides its memory-mapped files: 8.4 bytes per point
# traced on a simulated 0.5 km survey (10.9 M points), 3.2 on a 2 km one
VIEWER_MAP_BYTES_PER_POINT = 10.0
# surveys from which the map is built at import: 10.9 M points took 16 s to build (a simulated
# 0.5 km survey), 92.7 M 50 s; below this a first open builds it in a few seconds
PREPARE_VIEWER_MIN_POINTS = 5_000_000


def check_import_config(config: dict[str, Any], settings: Settings) -> Path:
    """Refused when queued: unknown options, a path outside the import root or missing; the
    path resolved inside the root."""
    unknown = sorted(set(config) - set(FIELDS))
    if unknown:
        raise ConfigError(f"config.{unknown[0]}", f"{KIND} takes {', '.join(FIELDS)}")
    path = config.get("path")
    if not isinstance(path, str):
        raise ConfigError("config.path", "must be the survey's path inside the import root")
    for key, longest in (("format", 32), ("name", 255)):  # the survey table's columns
        value = config.get(key)
        if value is not None and (not isinstance(value, str) or not value.strip()):
            raise ConfigError(f"config.{key}", "must be a non-empty string when given")
        if value is not None and len(value) > longest:
            raise ConfigError(f"config.{key}", f"has {len(value)} characters; at most {longest}")
    declared_sensor(config)
    return resolve_import_path(path, settings.allowed_import_root)


def declared_sensor(config: dict[str, Any]) -> SensorKind | None:
    """The sensor kind the config declares; None: told by the reader or the point times."""
    value = config.get("sensor")
    if value is None:
        return None
    try:
        return parse_sensor_kind(value, allow_unknown=False)
    except ValueError as exc:
        raise ConfigError("config.sensor", f"{exc} (or leave it out: detected)") from exc


@task(KIND, check=check_import_config)
def import_survey(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    source = check_import_config(config, context.settings)  # again: the folder may have changed
    context.progress(0.05, f"opening {source.name}")
    with Session(context.engine) as session:
        survey = import_source(
            session,
            source,
            config.get("format"),
            config.get("name"),
            context.user_id,
            "survey.import",
            sensor=declared_sensor(config),
            requested=config["path"],
            job_id=context.job_id,
        )
        queue_viewer_map(session, survey, context.user_id, context.settings)
        return {"survey_id": survey.id, "name": survey.name, "frames": survey.frame_count}


def queue_viewer_map(
    session: Session, survey: Survey, user_id: int | None, settings: Settings
) -> int | None:
    """Queue `prepare:viewer` for a survey just imported when building its map on the first
    open would keep that open waiting (`PREPARE_VIEWER_MIN_POINTS`); its job id, or None (a
    smaller survey, or one too large for the job memory limit: the viewer builds the map on
    its first open). A survey is not deleted while a job of it is queued or running, so a
    small one is not given one."""
    if survey.point_count < PREPARE_VIEWER_MIN_POINTS:
        return None
    try:
        return enqueue(session, PREPARE_VIEWER, {}, survey.id, user_id, settings).id
    except ConfigError:
        return None


def check_prepare_config(config: dict[str, Any], settings: Settings) -> None:
    if config:
        raise ConfigError(f"config.{sorted(config)[0]}", f"{PREPARE_VIEWER} takes no options")


def estimate_viewer_map(
    session: Session, survey: int | None, config: dict[str, Any]
) -> MemoryEstimate:
    """The map's build streams the frames into memory-mapped files; what it holds is the
    overview's candidates and the pillars' table (`VIEWER_MAP_BYTES_PER_POINT`)."""
    if survey is None:
        return MemoryEstimate("no survey")
    footprint = survey_footprint(session, survey)
    return MemoryEstimate(survey_text(footprint)).add(
        "survey_id",
        points_mb(footprint, VIEWER_MAP_BYTES_PER_POINT),
        f"{VIEWER_MAP_BYTES_PER_POINT:.0f} bytes per point of the survey",
    )


@task(PREPARE_VIEWER, check=check_prepare_config, estimate=estimate_viewer_map)
def prepare_viewer(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    check_prepare_config(config, context.settings)
    if context.survey_id is None:
        raise ConfigError("survey_id", f"{PREPARE_VIEWER} needs a survey")
    with Session(context.engine) as session:
        source = MapSource.of(get_survey(session, context.survey_id))
    context.progress(0.05, "building the viewer's map")
    survey_map = load_map(
        source, context.settings.cache_dir, context.settings.viewer_overview_points
    )
    return {"points": len(survey_map), "tiles": int(len(survey_map.tile_ids)),
            "overview_points": int(len(survey_map.overview))}  # fmt: skip
