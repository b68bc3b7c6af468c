"""Reading job records for lists (the queue in `app.jobs.queue` creates and moves them)."""

from __future__ import annotations

from sqlmodel import Session, select

from app.store.models import Job, JobStatus


def list_jobs(
    session: Session,
    status: JobStatus | None = None,
    survey_id: int | None = None,
    kind: str | None = None,
    limit: int = 50,
    offset: int = 0,
) -> list[Job]:
    """Jobs, newest first, filtered by whichever of status / survey / kind is given."""
    query = select(Job)
    if status is not None:
        query = query.where(Job.status == status)
    if survey_id is not None:
        query = query.where(Job.survey_id == survey_id)
    if kind is not None:
        query = query.where(Job.kind == kind)
    query = query.order_by(Job.created_at.desc(), Job.id.desc()).offset(offset).limit(limit)
    return list(session.exec(query).all())


def newest_job_of_kind(session: Session, kind: str) -> Job | None:
    """The job of KIND created last, whatever its status."""
    return session.exec(select(Job).where(Job.kind == kind).order_by(Job.created_at.desc())).first()


def pending_job_of_kind(session: Session, kind: str) -> Job | None:
    """A queued or running job of KIND, if any."""
    return session.exec(
        select(Job).where(Job.kind == kind, Job.status.in_([JobStatus.queued, JobStatus.running]))
    ).first()
