"""Job records: the new row, every change of its status, and the reads of lists and pending
work (`app.jobs.queue` checks what a job may be before it is queued).

Status changes race between the API (cancel, resume), worker processes (claim, progress, finish)
and the pool (interrupted workers), so each one is a single conditional UPDATE (`... WHERE id =
? AND status IN (...)`) rather than read-modify-write: whoever comes second changes nothing and
learns it from the row count. SQLite serialises writers, which makes `claim_next` exclusive.

    queued -> running -> succeeded | failed | cancelled
    queued -> cancelled                 running -> interrupted (worker or server died)
    interrupted | failed | cancelled -> queued (resume: same id, same config)
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

from app.core.errors import ConflictError, NotFoundError
from app.store.audit import audit, unused_id
from app.store.db import commit
from app.store.models import Job, JobStatus, utcnow

RESUMABLE = (JobStatus.interrupted, JobStatus.failed, JobStatus.cancelled)
ACTIVE = (JobStatus.queued, JobStatus.running)
JOB_SUCCEEDED = "job.succeeded"
SERVER_STOPPED = "interrupted: the server stopped while it ran; resume it to run it again"


def get_job(session: Session, job_id: int) -> Job:
    """The job as stored now (workers change jobs behind any session's back)."""
    job = session.get(Job, job_id, populate_existing=True)
    if job is None:
        raise NotFoundError(f"job {job_id} not found")
    return job


def _update(*where: Any) -> sa.Update:
    return sa.update(Job).where(*where).execution_options(synchronize_session=False)


def insert_job(
    session: Session,
    kind: str,
    config: dict[str, Any],
    survey_id: int | None,
    user_id: int | None,
    message: str,
) -> Job:
    """A new queued job row with an id never used before (flushed, not committed)."""
    job = Job(
        kind=kind, config=dict(config), survey_id=survey_id, created_by=user_id, message=message
    )
    job.id = unused_id(Job, "job")  # type: ignore[assignment]
    session.add(job)
    session.flush()
    return job


def claim_next(engine: Engine, worker_pid: int) -> Job | None:
    """Take the oldest queued job for this worker, or None; one statement, so two workers never
    get the same job."""
    oldest = (
        sa.select(Job.id)
        .where(Job.status == JobStatus.queued)
        .order_by(Job.created_at, Job.id)
        .limit(1)
        .scalar_subquery()
    )
    claim = (
        sa.update(Job)
        .where(Job.id == oldest, Job.status == JobStatus.queued)
        .values(
            status=JobStatus.running,
            started_at=utcnow(),
            finished_at=None,
            attempts=Job.attempts + 1,
            worker_pid=worker_pid,
            progress=0.0,
            message="started",
        )
        .returning(Job.id)
    )
    with engine.begin() as conn:
        job_id = conn.execute(claim).scalar()
    if job_id is None:
        return None
    with Session(engine, expire_on_commit=False) as session:
        return session.get(Job, job_id)


def any_queued(engine: Engine) -> bool:
    """Whether a job waits for a worker (the pool starts its workers for the first one)."""
    waiting = sa.select(Job.id).where(Job.status == JobStatus.queued).limit(1)
    with engine.connect() as conn:
        return conn.execute(waiting).first() is not None


def set_workdir(engine: Engine, job_id: int, log_path: str, result_path: str) -> None:
    with engine.begin() as conn:
        conn.execute(_update(Job.id == job_id).values(log_path=log_path, result_path=result_path))


def report_progress(engine: Engine, job_id: int, fraction: float, message: str) -> bool:
    """Record progress; True when the task should stop (cancel requested, or the job is no
    longer running, e.g. the pool gave up on it)."""
    fraction = min(max(float(fraction), 0.0), 1.0)
    with engine.begin() as conn:
        row = conn.execute(
            _update(Job.id == job_id, Job.status == JobStatus.running)
            .values(progress=fraction, message=message)
            .returning(Job.cancel_requested)
        ).first()
    return True if row is None else bool(row[0])


def finish(
    engine: Engine,
    job_id: int,
    status: JobStatus,
    message: str,
    result: dict[str, Any] | None = None,
) -> bool:
    """End a running job; False when it was no longer running (then nothing changes).

    A success leaves a `job.succeeded` audit event (kind, survey) in the same transaction, so
    whoever follows the audit log (the viewer's QA mode) sees new results once they are there.
    """
    values: dict[str, Any] = {"status": status, "message": message, "finished_at": utcnow()}
    if status == JobStatus.succeeded:
        values["progress"] = 1.0
    if result is not None:
        values["result"] = result
    with Session(engine) as session:
        done = session.execute(
            _update(Job.id == job_id, Job.status == JobStatus.running)
            .values(values)
            .returning(Job.kind, Job.survey_id)
        ).first()
        if done is not None and status == JobStatus.succeeded:
            audit(session, None, JOB_SUCCEEDED, "job", job_id, kind=done[0], survey_id=done[1])
        session.commit()
    return done is not None


def request_cancel(session: Session, job_id: int, user_id: int | None) -> Job:
    """Cancel: a queued (or interrupted) job at once, a running one at its next progress call;
    a finished job is a ConflictError. Audited and committed."""
    job = get_job(session, job_id)
    now = utcnow()
    stopped = session.execute(
        _update(Job.id == job_id, Job.status.in_([JobStatus.queued, JobStatus.interrupted])).values(
            status=JobStatus.cancelled, finished_at=now, message=f"cancelled by user {user_id}"
        )
    )
    if stopped.rowcount == 0:
        asked = session.execute(
            _update(Job.id == job_id, Job.status == JobStatus.running).values(
                cancel_requested=True, message=f"cancel requested by user {user_id}"
            )
        )
        if asked.rowcount == 0:
            session.rollback()
            session.refresh(job)
            raise ConflictError(f"job {job_id} is already {job.status.value}; nothing to cancel")
    audit(session, user_id, "job.cancel", "job", job_id, was=job.status.value)
    commit(session)
    session.refresh(job)
    return job


def mark_interrupted(
    engine: Engine, worker_pids: Iterable[int] | None = None, message: str = SERVER_STOPPED
) -> int:
    """Running jobs whose worker is gone -> interrupted (cancelled when a cancel was pending).

    Without `worker_pids`: every running job (server start: no worker of ours can be alive).
    Returns how many jobs were interrupted."""
    where = [Job.status == JobStatus.running]
    if worker_pids is not None:
        where.append(Job.worker_pid.in_(list(worker_pids)))
    now = utcnow()
    with engine.begin() as conn:
        conn.execute(
            _update(*where, Job.cancel_requested).values(
                status=JobStatus.cancelled, finished_at=now, message="cancelled"
            )
        )
        done = conn.execute(
            _update(*where).values(status=JobStatus.interrupted, finished_at=now, message=message)
        )
    return done.rowcount


def resume(session: Session, job_id: int, user_id: int | None) -> Job:
    """Queue an interrupted, failed or cancelled job again: same id and config, attempts go on,
    its log is appended to. Audited and committed."""
    job = get_job(session, job_id)
    queued = session.execute(
        _update(Job.id == job_id, Job.status.in_(RESUMABLE)).values(
            status=JobStatus.queued,
            progress=0.0,
            message=f"resumed by user {user_id}",
            cancel_requested=False,
            finished_at=None,
            worker_pid=None,
            result={},
        )
    )
    if queued.rowcount == 0:
        session.rollback()
        session.refresh(job)
        raise ConflictError(
            f"job {job_id} is {job.status.value}; only interrupted, failed or cancelled jobs "
            "can be resumed"
        )
    audit(session, user_id, "job.resume", "job", job_id, was=job.status.value)
    commit(session)
    session.refresh(job)
    return job


def cancel_requests(engine: Engine) -> list[tuple[int, int | None, str | None]]:
    """(job id, worker pid, workdir) of the running jobs whose cancel was requested."""
    with engine.connect() as conn:
        rows = conn.execute(
            sa.select(Job.id, Job.worker_pid, Job.result_path).where(
                Job.status == JobStatus.running, Job.cancel_requested
            )
        ).all()
    return [tuple(row) for row in rows]


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


def newest_job_of_kind(session: Session, kind: str, status: JobStatus | None = None) -> Job | None:
    """The job of KIND created last (with STATUS, else whatever its status)."""
    query = select(Job).where(Job.kind == kind)
    if status is not None:
        query = query.where(Job.status == status)
    return session.exec(query.order_by(Job.created_at.desc())).first()


def pending_job_of_kind(session: Session, kind: str) -> Job | None:
    """A queued or running job of KIND, if any."""
    return session.exec(
        select(Job).where(Job.kind == kind, Job.status.in_([JobStatus.queued, JobStatus.running]))
    ).first()
