"""`/models`: trained model versions with their validation metrics, promotion, retraining."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field
from sqlmodel import Session

from app.api.deps import Admin, CurrentUser, SessionDep, SettingsDep
from app.api.errors import errors
from app.api.types import Id
from app.core.errors import ConfigError
from app.core.sensors import SensorKind
from app.jobs.clutter_tasks import SEGMENTATION_UPSTREAM, segmentation_weights
from app.jobs.queue import enqueue
from app.jobs.registry import check_config
from app.jobs.retraining import readiness, retraining_state
from app.store.model_versions import get_version, list_versions, promote_version
from app.store.models import ModelVersionBase, Pipeline

router = APIRouter(prefix="/models", tags=["models"], responses=errors(401))

TRAINABLE = {Pipeline.phantom: "train:phantom", Pipeline.guardrail: "train:guardrail"}


class ModelVersionPublic(ModelVersionBase):
    model_config = ConfigDict(json_schema_serialization_defaults_required=True)  # all answered

    id: int
    version: int
    sensor_kind: SensorKind = Field(description="the scanner kind it was trained for")


class RetrainRequest(BaseModel):
    pipeline: Pipeline
    config: dict[str, Any] = Field(default_factory=dict)


class JobRef(BaseModel):
    job_id: int
    kind: str
    status: str


class TrainingReadiness(BaseModel):
    pipeline: Pipeline
    blocked_by: str | None = Field(
        description="what keeps a retraining from training on the labels now; null: ready"
    )
    last_job_id: int | None = Field(description="its newest training job")
    last_job_status: str | None
    last_job_message: str | None = Field(description="how that job ended (a failure's reason)")


class RetrainingStatus(BaseModel):
    threshold: int = Field(description="new human labels that queue retraining; 0 = off")
    new_labels: int = Field(description="human labels since the last training that succeeded")
    pending_job_id: int | None
    blocked_by: str | None = Field(
        None, description="why the due retraining was not queued (checked once it is due)"
    )
    pipelines: list[TrainingReadiness] = Field(
        default_factory=list, description="per trainable pipeline, whether retraining can run"
    )


def training_readiness(session: Session, pipeline: Pipeline) -> TrainingReadiness:
    ready = readiness(session, pipeline.value)
    job = ready.last_job
    return TrainingReadiness(
        pipeline=pipeline,
        blocked_by=ready.blocked_by,
        last_job_id=None if job is None else job.id,
        last_job_status=None if job is None else job.status.value,
        last_job_message=None if job is None else job.message,
    )


@router.get("", response_model=list[ModelVersionPublic])
def list_models(
    _: CurrentUser, session: SessionDep, pipeline: Pipeline | None = None
) -> list[ModelVersionPublic]:
    """Model versions, newest first, with validation metrics on held-out labels."""
    return [ModelVersionPublic.model_validate(m) for m in list_versions(session, pipeline)]


@router.get("/retraining", response_model=RetrainingStatus)
def retraining(_: CurrentUser, session: SessionDep, settings: SettingsDep) -> RetrainingStatus:
    """How many reviewed labels came in since the last training that succeeded, the trigger,
    and per trainable pipeline whether a retraining can train now and how the last one ended."""
    pipelines = [training_readiness(session, p) for p in TRAINABLE]
    return RetrainingStatus(**retraining_state(session, settings).__dict__, pipelines=pipelines)


class SegmentationWeights(BaseModel):
    available: bool = Field(description="the clutter pipeline's camera masks can run")
    file: str = Field(description="where the server looks for the weights")
    upstream: str = Field(description="where to get them (MMSCLEAN_WEIGHTS_DIR: their folder)")


@router.get("/segmentation", response_model=SegmentationWeights)
def segmentation(_: CurrentUser, settings: SettingsDep) -> SegmentationWeights:
    """Whether the clutter pipeline's image segmentation weights are on this server (they are
    never downloaded at run time), so the dashboard can say so next to the camera option."""
    available, path = segmentation_weights(settings)
    return SegmentationWeights(available=available, file=str(path), upstream=SEGMENTATION_UPSTREAM)


@router.get("/{model_id}", response_model=ModelVersionPublic, responses=errors(404))
def get_model(model_id: Id, _: CurrentUser, session: SessionDep) -> ModelVersionPublic:
    return ModelVersionPublic.model_validate(get_version(session, model_id))


@router.post("/{model_id}/promote", response_model=ModelVersionPublic, responses=errors(403, 404))
def promote(model_id: Id, admin: Admin, session: SessionDep) -> ModelVersionPublic:
    """Make this version the one its pipeline runs with (admin; metrics are not checked)."""
    return ModelVersionPublic.model_validate(promote_version(session, model_id, admin.id))


@router.post("/retrain", response_model=JobRef, status_code=202, responses=errors(403, 422))
def retrain(
    body: RetrainRequest, admin: Admin, session: SessionDep, settings: SettingsDep
) -> JobRef:
    """Queue a training job on the reviewed labels now (admin)."""
    kind = TRAINABLE.get(body.pipeline)
    if kind is None:
        raise ConfigError("pipeline", f"{body.pipeline.value} has no trainable model")
    check_config(kind, body.config, settings)  # a bad config's field before the labels' state
    blocked = readiness(session, body.pipeline.value, body.config).blocked_by
    if blocked is not None:  # refused now, not a job bound to fail
        raise ConfigError("labels", blocked)
    job = enqueue(session, kind, body.config, None, admin.id, settings)
    return JobRef(job_id=job.id, kind=job.kind, status=job.status.value)
