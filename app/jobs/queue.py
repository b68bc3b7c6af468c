"""The job queue's front door: a job's kind, survey, config, model and memory are checked when
it is queued (so a bad one is a 422, not a failed job); the job rows and every change of their
status live in `app.store.jobs`."""

from __future__ import annotations

from typing import Any

from sqlmodel import Session

from app.core.errors import ConfigError, ConflictError
from app.core.settings import Settings, get_settings
from app.jobs.memory import check_memory
from app.jobs.registry import ESTIMATES, MODELS, check_config, task_for
from app.jobs.task_config import job_model
from app.store.audit import audit
from app.store.db import commit
from app.store.jobs import ACTIVE, get_job, insert_job
from app.store.models import Job, Pipeline
from app.store.surveys import survey_exists


def _new_job(
    session: Session,
    kind: str,
    config: dict[str, Any],
    survey_id: int | None,
    user_id: int | None,
    settings: Settings | None,
    message: str,
) -> Job:
    task_for(kind)  # ConfigError('kind') for an unknown kind
    if not isinstance(config, dict):
        raise ConfigError("config", "must be a JSON object")
    if survey_id is not None and not survey_exists(session, survey_id):
        raise ConfigError("survey_id", f"no survey with id {survey_id}")
    if survey_id is None and kind.startswith("run:"):
        raise ConfigError("survey_id", f"{kind} jobs need a survey")
    settings = settings or get_settings()
    check_config(kind, config, settings)
    if kind in MODELS and config.get("model_id") is not None:
        job_model(session, Pipeline(MODELS[kind]), config["model_id"])
    if kind in ESTIMATES:
        check_memory(ESTIMATES[kind](session, survey_id, config), settings.job_memory_mb)
    return insert_job(session, kind, config, survey_id, user_id, message)


def enqueue(
    session: Session,
    kind: str,
    config: dict[str, Any],
    survey_id: int | None,
    user_id: int | None,
    settings: Settings | None = None,
) -> Job:
    """Queue a new job (kind and config checked now, so a bad one is a 422, not a failed job);
    audited and committed."""
    job = _new_job(session, kind, config, survey_id, user_id, settings, "queued")
    audit(session, user_id, "job.create", "job", job.id, kind=kind, survey_id=survey_id)
    commit(session)
    session.refresh(job)
    return job


def requeue(
    session: Session, job_id: int, user_id: int | None, settings: Settings | None = None
) -> Job:
    """A new job with the same kind, survey and config (the old one keeps its record)."""
    old = get_job(session, job_id)
    if old.status in ACTIVE:
        raise ConflictError(f"job {job_id} is still {old.status.value}; cancel it first")
    job = _new_job(
        session,
        old.kind,
        dict(old.config),
        old.survey_id,
        user_id,
        settings,
        f"queued (again, from job {job_id})",
    )
    audit(session, user_id, "job.requeue", "job", job.id, from_job=job_id, kind=old.kind)
    commit(session)
    session.refresh(job)
    return job
