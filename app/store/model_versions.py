"""Model versions: the shipped checkpoints and the ones retraining produced, with their
validation metrics and the sensor kind they were trained for; one promoted version per pipeline
and sensor kind is what the pipeline runs with on surveys of that kind."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlmodel import Session, select

from app.core.errors import NotFoundError
from app.core.sensors import SensorKind
from app.pipelines.sensor_models import card_sensor_kind
from app.store.audit import audit
from app.store.db import commit
from app.store.models import ModelVersion, Pipeline, utcnow


def list_versions(session: Session, pipeline: Pipeline | None = None) -> list[ModelVersion]:
    """Model versions (of PIPELINE, or all), newest first."""
    query = select(ModelVersion).order_by(ModelVersion.id.desc())
    if pipeline is not None:
        query = query.where(ModelVersion.pipeline == pipeline)
    return list(session.exec(query).all())


def get_version(session: Session, version_id: int) -> ModelVersion:
    version = session.get(ModelVersion, version_id)
    if version is None:
        raise NotFoundError(f"model version {version_id} not found")
    return version


def promoted_version(
    session: Session, pipeline: Pipeline, sensor_kind: SensorKind
) -> ModelVersion | None:
    query = select(ModelVersion).where(
        ModelVersion.pipeline == pipeline,
        ModelVersion.sensor_kind == sensor_kind.value,
        ModelVersion.is_promoted,
    )
    return session.exec(query.order_by(ModelVersion.id.desc())).first()


def version_by_checkpoint(
    session: Session, pipeline: Pipeline, checkpoint: Path
) -> ModelVersion | None:
    """The pipeline's version row of the checkpoint file at CHECKPOINT (as given), if any."""
    query = select(ModelVersion).where(
        ModelVersion.pipeline == pipeline, ModelVersion.checkpoint_path == str(checkpoint)
    )
    return session.exec(query).first()


def ensure_shipped_version(
    session: Session, pipeline: Pipeline, checkpoint: Path, card: dict[str, Any]
) -> ModelVersion:
    """The row of a checkpoint shipped in models/ (created on first use, promoted when the
    pipeline has no promoted version for its sensor kind yet); commits."""
    checkpoint = Path(checkpoint).resolve()
    kind = card_sensor_kind(card)
    name = f"shipped:{checkpoint.name}"
    existing = session.exec(
        select(ModelVersion).where(ModelVersion.pipeline == pipeline, ModelVersion.name == name)
    ).first()
    if existing is not None:
        return existing
    version = ModelVersion(
        pipeline=pipeline,
        name=name,
        checkpoint_path=str(checkpoint),
        metrics={"validation": card.get("validation", {})},
        trained_on={"shipped": True, "created": card.get("created")},
        # a model of unknown kind is never picked by kind: only by its id, by hand
        is_promoted=kind is not SensorKind.UNKNOWN
        and promoted_version(session, pipeline, kind) is None,
        sensor_kind=kind.value,
    )
    session.add(version)
    commit(session)
    session.refresh(version)
    return version


def register_version(
    session: Session,
    pipeline: Pipeline,
    name: str,
    checkpoint: Path,
    metrics: dict[str, Any],
    trained_on: dict[str, Any],
    job_id: int | None,
    promote: bool,
    sensor_kind: SensorKind,
) -> ModelVersion:
    """Record a newly trained checkpoint for SENSOR_KIND; with `promote` it replaces the
    promoted one of that kind."""
    version = ModelVersion(
        pipeline=pipeline,
        name=name,
        checkpoint_path=str(Path(checkpoint).resolve()),
        metrics=metrics,
        trained_on=trained_on,
        job_id=job_id,
        sensor_kind=sensor_kind.value,
    )
    session.add(version)
    session.flush()
    if promote:
        _promote(session, version)
    audit(
        session,
        None,
        "model.register",
        "model_version",
        version.id,
        pipeline=pipeline.value,
        sensor_kind=sensor_kind.value,
        promoted=promote,
        job_id=job_id,
    )
    commit(session)
    session.refresh(version)
    return version


def _promote(session: Session, version: ModelVersion) -> None:
    for other in session.exec(
        select(ModelVersion).where(
            ModelVersion.pipeline == version.pipeline,
            ModelVersion.sensor_kind == version.sensor_kind,
            ModelVersion.is_promoted,
            ModelVersion.id != version.id,
        )
    ).all():
        other.is_promoted = False
        session.add(other)
    version.is_promoted = True
    version.metrics = {**version.metrics, "promoted_at": utcnow().isoformat()}
    session.add(version)


def promote_version(session: Session, version_id: int, user_id: int | None) -> ModelVersion:
    """An admin's promotion, whatever the metrics say; commits."""
    version = get_version(session, version_id)
    _promote(session, version)
    audit(session, user_id, "model.promote", "model_version", version.id, by="admin")
    commit(session)
    session.refresh(version)
    return version
