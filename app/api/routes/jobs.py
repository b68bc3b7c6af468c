"""`/jobs`: start pipeline and training jobs, watch their progress, cancel, resume, fetch results.

The API only writes job rows; worker processes (app.jobs.pool) pick them up, so a long job
never holds up a request. Annotators may start `run:*` and other non-training jobs and control
their own; reviewers and admins control anyone's; `train:*` jobs are for admins.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Query, Response
from fastapi.responses import FileResponse, PlainTextResponse
from pydantic import BaseModel, Field

from app.api.deps import Annotator, CurrentUser, SessionDep, SettingsDep
from app.api.downloads import check_download, may_download
from app.api.errors import errors
from app.api.schemas import JobPublic
from app.api.types import FilePath, Id, Offset
from app.core.errors import MmscleanError, NotFoundError, PermissionDeniedError
from app.core.settings import Settings
from app.jobs.queue import enqueue, requeue
from app.store import jobs as store_jobs
from app.store.jobs import get_job, request_cancel, resume
from app.store.models import Job, JobStatus, Role, User
from app.store.users import has_role

router = APIRouter(prefix="/jobs", tags=["jobs"], responses=errors(401))

MAX_TAIL = 100_000


class JobCreate(BaseModel):
    kind: str = Field(min_length=1, max_length=64, description="e.g. run:phantom, train:phantom")
    survey_id: Id | None = Field(None, description="the survey a run:* job works on")
    config: dict[str, Any] = Field(default_factory=dict, description="the kind's options")


class JobFile(BaseModel):
    name: str = Field(description="path relative to the job folder: GET /jobs/{id}/files/{name}")
    size: int


class JobResults(BaseModel):
    job_id: int
    status: JobStatus
    result: dict[str, Any]
    files: list[JobFile]


def may_start(user: User, kind: str) -> None:
    if kind.startswith("train:") and not has_role(user, Role.admin):
        raise PermissionDeniedError(
            f"user {user.username!r} is {user.role.value}; {kind} jobs need the admin role"
        )


def may_control(user: User, job: Job) -> None:
    may_start(user, job.kind)
    if job.created_by != user.id and not has_role(user, Role.reviewer):
        raise PermissionDeniedError(
            f"job {job.id} was started by another user; only reviewers and admins may change it"
        )


def workdir_of(job: Job, settings: Settings) -> Path:
    return Path(job.result_path or settings.jobs_dir / str(job.id)).resolve()


@router.post("", response_model=JobPublic, status_code=201, responses=errors(403, 422))
def create_job(
    body: JobCreate, user: Annotator, session: SessionDep, settings: SettingsDep
) -> JobPublic:
    """Queue a job; a worker starts it when one is free. Kind, survey and config are checked
    now (422 names the field)."""
    may_start(user, body.kind)
    job = enqueue(session, body.kind, body.config, body.survey_id, user.id, settings)
    return JobPublic.model_validate(job)


@router.get("", response_model=list[JobPublic], responses=errors(422))
def list_jobs(
    _: CurrentUser,
    session: SessionDep,
    status: JobStatus | None = None,
    survey_id: Id | None = None,
    kind: str | None = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    offset: Offset = 0,
) -> list[JobPublic]:
    """Jobs, newest first."""
    jobs = store_jobs.list_jobs(session, status, survey_id, kind, limit, offset)
    return [JobPublic.model_validate(j) for j in jobs]


@router.get("/{job_id}", response_model=JobPublic, responses=errors(404))
def read_job(job_id: Id, _: CurrentUser, session: SessionDep) -> JobPublic:
    """Status, progress, message, timings and (once succeeded) the result summary."""
    return JobPublic.model_validate(get_job(session, job_id))


@router.get(
    "/{job_id}/log",
    response_class=Response,  # errors stay JSON; the log itself is text/plain
    responses={
        **errors(404, 422),
        200: {"content": {"text/plain": {"schema": {"type": "string"}}}, "description": "log"},
    },
)
def read_log(
    job_id: Id,
    _: CurrentUser,
    session: SessionDep,
    settings: SettingsDep,
    tail: Annotated[int | None, Query(ge=1, le=MAX_TAIL, description="last N lines")] = None,
) -> PlainTextResponse:
    """The job's log (every attempt, appended); empty before a worker started it."""
    job = get_job(session, job_id)
    path = Path(job.log_path) if job.log_path else workdir_of(job, settings) / "job.log"
    if not path.is_file():
        return PlainTextResponse("")
    with path.open(encoding="utf-8", errors="replace") as lines:
        text = "".join(deque(lines, maxlen=tail) if tail else lines)
    return PlainTextResponse(text)


@router.post("/{job_id}/cancel", response_model=JobPublic, responses=errors(403, 404, 409))
def cancel_job(job_id: Id, user: Annotator, session: SessionDep) -> JobPublic:
    """Cancel: a queued job at once, a running one at its next progress report (409 when it
    already ended)."""
    may_control(user, get_job(session, job_id))
    return JobPublic.model_validate(request_cancel(session, job_id, user.id))


@router.post("/{job_id}/resume", response_model=JobPublic, responses=errors(403, 404, 409))
def resume_job(job_id: Id, user: Annotator, session: SessionDep) -> JobPublic:
    """Queue an interrupted, failed or cancelled job again under the same id and config."""
    may_control(user, get_job(session, job_id))
    return JobPublic.model_validate(resume(session, job_id, user.id))


@router.post(
    "/{job_id}/requeue",
    response_model=JobPublic,
    status_code=201,
    responses=errors(403, 404, 409, 422),
)
def requeue_job(
    job_id: Id, user: Annotator, session: SessionDep, settings: SettingsDep
) -> JobPublic:
    """A new job with the same kind, survey and config (409 while the old one is active)."""
    may_start(user, get_job(session, job_id).kind)
    return JobPublic.model_validate(requeue(session, job_id, user.id, settings))


@router.get("/{job_id}/results", response_model=JobResults, responses=errors(404))
def read_results(
    job_id: Id, user: CurrentUser, session: SessionDep, settings: SettingsDep
) -> JobResults:
    """The result summary and every file the job wrote that the user may download (with
    /files/{name}; annotators: logs and reports, as for the survey exports)."""
    job = get_job(session, job_id)
    workdir = workdir_of(job, settings)
    found = sorted(p for p in workdir.rglob("*") if p.is_file()) if workdir.is_dir() else []
    paths = [p for p in found if may_download(user, p.name)]
    files = [JobFile(name=p.relative_to(workdir).as_posix(), size=p.stat().st_size) for p in paths]
    return JobResults(job_id=job.id, status=job.status, result=dict(job.result), files=files)


@router.get(
    "/{job_id}/files/{name:path}",
    response_class=FileResponse,
    responses={**errors(400, 403, 404), 200: {"content": {"application/octet-stream": {}}}},
)
def download_file(
    job_id: Id, name: FilePath, user: CurrentUser, session: SessionDep, settings: SettingsDep
) -> FileResponse:
    """One file of the job's folder; a name leading outside it is refused (400). Maps, meshes
    and label arrays are for reviewers, as the survey exports (403); logs and reports for all."""
    workdir = workdir_of(get_job(session, job_id), settings)
    target = (workdir / name).resolve()
    if not target.is_relative_to(workdir):
        raise MmscleanError(f"{name}: outside the folder of job {job_id}")
    check_download(user, target.name)
    if not target.is_file():
        raise NotFoundError(f"job {job_id} has no file {name}")
    return FileResponse(target, filename=target.name)
