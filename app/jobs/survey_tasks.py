"""`import:survey`: register a survey from a server path as a job, for drives whose opening takes
long (a KITTI raw drive without OXTS gets its poses from LiDAR odometry first: 1.6 s for the
20-frame sample drive, uncached). The import route of the API does the same in the request;
both go through `app.review.surveys.import_source`. Config: `path` (inside the import root),
optional `format`, `name` and `sensor` (rotating / profile; detected when absent); result: the
new survey's id and name.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlmodel import Session

from app.core.errors import ConfigError
from app.core.sensors import SensorKind, parse_sensor_kind
from app.core.settings import Settings
from app.io.import_root import resolve_import_path
from app.jobs.registry import JobContext, task
from app.review.surveys import import_source

KIND = "import:survey"
FIELDS = ("path", "format", "name", "sensor")


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
        return {"survey_id": survey.id, "name": survey.name, "frames": survey.frame_count}
