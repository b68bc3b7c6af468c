"""Which registered model version a pipeline job runs: the one `config.model_id` names (forced:
the report says when it is off-domain), else the promoted version for the survey's sensor kind,
else the shipped checkpoint for that kind (its row made on first use). With no model for the
kind, or a survey whose kind nobody told, the job stops with one line (`sensor_models`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from sqlmodel import Session

from app.core.errors import ConfigError, ConflictError
from app.core.sensors import SensorKind, parse_sensor_kind
from app.io import open_survey
from app.io.sensor_kind import detect_sensor_kind
from app.jobs.task_config import job_model
from app.pipelines.sensor_models import ModelChoice, choose_shipped, require_known_kind
from app.store.model_versions import ensure_shipped_version, promoted_version, version_by_checkpoint
from app.store.models import ModelVersion, Pipeline, Survey
from app.store.surveys import get_survey, set_sensor_kind


def survey_sensor_kind(session: Session, survey: Survey) -> SensorKind:
    """The survey's stored kind; a survey registered before kinds existed (unknown, never
    looked at) is told now from its reader or point times, and the answer kept."""
    if survey.sensor_kind == SensorKind.UNKNOWN and not survey.sensor_note:
        detection = detect_sensor_kind(open_survey(survey.source_path, survey.format))
        assert survey.id is not None
        survey = set_sensor_kind(session, survey.id, detection.kind, None, detection.reason)
    return parse_sensor_kind(survey.sensor_kind)


def model_for_job(
    session: Session,
    pipeline: Pipeline,
    survey: Survey,
    model_id: int | None,
    shipped: Mapping[SensorKind, Path],
    card_of: Callable[[Path], dict[str, Any]],
) -> tuple[ModelVersion, ModelChoice]:
    """The version row to run and the choice the report records (module docstring)."""
    kind = survey_sensor_kind(session, survey)
    if model_id is not None:
        version = job_model(session, pipeline, model_id)
        model_kind = parse_sensor_kind(version.sensor_kind)
        return version, ModelChoice(Path(version.checkpoint_path), model_kind, kind, forced=True)
    require_known_kind(survey.name, kind, survey.sensor_note)
    version = current_version(session, pipeline, kind, shipped, card_of, f"survey {survey.name}")
    return version, ModelChoice(Path(version.checkpoint_path), kind, kind, forced=False)


def current_version(
    session: Session,
    pipeline: Pipeline,
    kind: SensorKind,
    shipped: Mapping[SensorKind, Path],
    card_of: Callable[[Path], dict[str, Any]],
    what: str,
) -> ModelVersion:
    """The promoted version for KIND, else the shipped checkpoint's row (made on first use);
    a run uses it, retraining starts from it. One line naming `what` the model is for when
    there is none for KIND."""
    promoted = promoted_version(session, pipeline, kind)
    if promoted is not None and Path(promoted.checkpoint_path).is_file():
        return promoted
    choice = choose_shipped(pipeline.value, shipped, what, kind)
    path = choice.path.resolve()
    known = version_by_checkpoint(session, pipeline, path)
    if known is None:
        try:
            known = ensure_shipped_version(session, pipeline, path, card_of(path))
        except ConflictError:  # another worker made the row a moment ago
            known = version_by_checkpoint(session, pipeline, path)
            if known is None:
                raise
    return known


def retraining_kind(
    session: Session, survey_ids: Iterable[int], wanted: str | None
) -> tuple[SensorKind, list[int]]:
    """The sensor kind a retraining job trains for (`wanted`, else the one kind of the labelled
    surveys) and the surveys whose labels it may use: a model learns one scanner's pattern."""
    kinds = {sid: survey_sensor_kind(session, get_survey(session, sid)) for sid in survey_ids}
    if wanted is not None:
        kind = parse_sensor_kind(wanted, allow_unknown=False)
        return kind, [sid for sid, k in kinds.items() if k == kind]
    unknown = sorted(sid for sid, k in kinds.items() if k is SensorKind.UNKNOWN)
    if unknown:
        raise ConfigError(
            "labels",
            f"survey(s) {', '.join(map(str, unknown))} have no sensor kind; declare it first",
        )
    found = sorted({k.value for k in kinds.values()})
    if len(found) > 1:
        raise ConfigError(
            "config.sensor_kind",
            f"the labels come from {' and '.join(found)} surveys; retrain one kind at a time",
        )
    kind = SensorKind(found[0]) if found else SensorKind.PROFILE
    return kind, list(kinds)
