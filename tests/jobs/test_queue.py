"""Queue semantics on a real SQLite file: claim, progress, cancel, interrupt, resume, requeue."""

from __future__ import annotations

import multiprocessing
import threading
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor

import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

import tests.jobs.sample_tasks  # noqa: F401  (registers the test:* kinds)
from app.core.errors import ConfigError, ConflictError, NotFoundError
from app.core.settings import Settings
from app.jobs.queue import enqueue, requeue
from app.pipelines.guardrail.pipeline import DEFAULT_MODEL as DEFAULT_CLASSIFIER
from app.pipelines.phantom.model import PAPER_MODEL
from app.store.db import make_engine
from app.store.jobs import (
    claim_next,
    finish,
    mark_interrupted,
    report_progress,
    request_cancel,
    resume,
)
from app.store.model_versions import ensure_shipped_version
from app.store.models import AuditEvent, Job, JobStatus, Pipeline, Survey


@pytest.fixture
def session(engine: Engine) -> Iterator[Session]:
    with Session(engine, expire_on_commit=False) as session:
        yield session


def queue_steps(session: Session, settings: Settings, n: int = 1) -> list[Job]:
    return [enqueue(session, "test:steps", {"steps": 2}, None, None, settings) for _ in range(n)]


def reload(engine: Engine, job_id: int) -> Job:
    with Session(engine) as session:
        return session.get(Job, job_id)


def test_enqueue_records_and_audits(session: Session, settings: Settings) -> None:
    job = enqueue(session, "test:steps", {"steps": 3}, None, None, settings)
    assert job.id is not None and job.status == JobStatus.queued and job.config == {"steps": 3}
    events = session.exec(select(AuditEvent).where(AuditEvent.action == "job.create")).all()
    assert [e.entity_id for e in events] == [str(job.id)]


def test_a_deleted_jobs_id_is_not_handed_out_again(session: Session, settings: Settings) -> None:
    """SQLite would reuse the highest rowid; the new job must not inherit the old one's events."""
    old = enqueue(session, "test:steps", {"steps": 2}, None, None, settings)
    session.delete(old)
    session.commit()
    new = enqueue(session, "test:steps", {"steps": 2}, None, None, settings)
    assert new.id == old.id + 1
    events = session.exec(select(AuditEvent.entity_id).where(AuditEvent.entity == "job")).all()
    assert events == [str(old.id), str(new.id)]


@pytest.mark.parametrize(
    ("kind", "config", "survey_id", "field"),
    [
        ("no:such-kind", {}, None, "kind"),
        ("test:steps", {"steps": 0}, None, "config.steps"),
        ("test:steps", {}, 999, "survey_id"),
        ("run:phantom", {}, None, "survey_id"),
    ],
)
def test_enqueue_refuses_bad_input_naming_the_field(
    session: Session, settings: Settings, kind: str, config: dict, survey_id: int | None, field: str
) -> None:
    with pytest.raises(ConfigError) as caught:
        enqueue(session, kind, config, survey_id, None, settings)
    assert caught.value.field == field
    assert session.exec(select(Job)).all() == []


def test_run_phantom_config_is_checked_when_queued(session: Session, settings: Settings) -> None:
    survey = Survey(name="s", format="sim", source_path="/nowhere")
    session.add(survey)
    session.commit()
    phantom = ensure_shipped_version(session, Pipeline.phantom, PAPER_MODEL, {})
    guardrail = ensure_shipped_version(session, Pipeline.guardrail, DEFAULT_CLASSIFIER, {})
    for config, field in (
        ({"model_path": "/etc/passwd"}, "config.model_path"),
        ({"model_path": "models/phantom/phantom_cnn.pt"}, "config.model_path"),
        ({"model_id": guardrail.id}, "config.model_id"),  # another pipeline's model
        ({"model_id": guardrail.id + 100}, "config.model_id"),  # no such version
        ({"dense": "maybe"}, "config.dense"),
        ({"threads": 3}, "config.threads"),
    ):
        with pytest.raises(ConfigError) as caught:
            enqueue(session, "run:phantom", config, survey.id, None, settings)
        assert caught.value.field == field
    chosen = {"model_id": phantom.id, "dense": False}
    assert enqueue(session, "run:phantom", chosen, survey.id, None, settings).id
    with pytest.raises(ConfigError) as caught:  # every kind refuses a checkpoint path
        enqueue(session, "run:clutter", {"model_path": "x.pt"}, survey.id, None, settings)
    assert caught.value.field == "config.model_path"


def test_claim_takes_oldest_and_counts_attempts(
    engine: Engine, session: Session, settings: Settings
) -> None:
    first, second = queue_steps(session, settings, 2)
    claimed = claim_next(engine, 4242)
    assert claimed.id == first.id
    assert claimed.status == JobStatus.running
    assert (claimed.worker_pid, claimed.attempts) == (4242, 1)
    assert claimed.started_at is not None
    assert claim_next(engine, 4243).id == second.id
    assert claim_next(engine, 4244) is None


def _claim_all(url: str) -> list[int]:
    engine = make_engine(url)
    mine = []
    while (job := claim_next(engine, multiprocessing.current_process().pid)) is not None:
        mine.append(job.id)
    engine.dispose()
    return mine


def test_claim_is_exclusive_between_processes(session: Session, settings: Settings) -> None:
    ids = {j.id for j in queue_steps(session, settings, 60)}
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(3, mp_context=spawn) as pool:
        results = list(pool.map(_claim_all, [settings.database_url] * 3))
    claimed = [i for part in results for i in part]
    assert sorted(claimed) == sorted(ids)  # every job once, none twice


def test_claim_is_exclusive_between_threads(
    engine: Engine, session: Session, settings: Settings
) -> None:
    ids = {j.id for j in queue_steps(session, settings, 40)}
    claimed: list[int] = []
    lock = threading.Lock()

    def claim(pid: int) -> None:
        while (job := claim_next(engine, pid)) is not None:
            with lock:
                claimed.append(job.id)

    threads = [threading.Thread(target=claim, args=(pid,)) for pid in (1, 2, 3, 4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(claimed) == sorted(ids)


def test_progress_and_finish(engine: Engine, session: Session, settings: Settings) -> None:
    (job,) = queue_steps(session, settings)
    assert report_progress(engine, job.id, 0.5, "half") is True  # not running yet: stop
    claim_next(engine, 1)
    assert report_progress(engine, job.id, 1.7, "clamped") is False
    assert reload(engine, job.id).progress == 1.0
    assert finish(engine, job.id, JobStatus.succeeded, "done", {"n": 1}) is True
    done = reload(engine, job.id)
    assert (done.status, done.result, done.message) == (JobStatus.succeeded, {"n": 1}, "done")
    assert done.finished_at is not None
    assert finish(engine, job.id, JobStatus.failed, "late") is False  # only running jobs end
    assert report_progress(engine, job.id, 0.2, "late") is True
    with Session(engine) as check:
        events = check.exec(select(AuditEvent).where(AuditEvent.action == "job.succeeded")).all()
    assert [(e.entity_id, e.payload) for e in events] == [
        (str(job.id), {"kind": "test:steps", "survey_id": None})
    ]


def test_only_a_success_is_announced(engine: Engine, session: Session, settings: Settings) -> None:
    failed, cancelled = queue_steps(session, settings, 2)
    claim_next(engine, 1)
    claim_next(engine, 1)
    assert finish(engine, failed.id, JobStatus.failed, "boom") is True
    assert finish(engine, cancelled.id, JobStatus.cancelled, "cancelled") is True
    with Session(engine) as check:
        assert not check.exec(select(AuditEvent).where(AuditEvent.action == "job.succeeded")).all()


def test_cancel_queued_at_once(engine: Engine, session: Session, settings: Settings) -> None:
    (job,) = queue_steps(session, settings)
    cancelled = request_cancel(session, job.id, None)
    assert cancelled.status == JobStatus.cancelled and cancelled.finished_at is not None
    assert claim_next(engine, 1) is None
    with pytest.raises(ConflictError, match="already cancelled"):
        request_cancel(session, job.id, None)
    actions = session.exec(select(AuditEvent.action)).all()
    assert "job.cancel" in actions


def test_cancel_running_reaches_the_task(
    engine: Engine, session: Session, settings: Settings
) -> None:
    (job,) = queue_steps(session, settings)
    claim_next(engine, 1)
    asked = request_cancel(session, job.id, None)
    assert asked.status == JobStatus.running and asked.cancel_requested
    assert report_progress(engine, job.id, 0.3, "working") is True
    finish(engine, job.id, JobStatus.cancelled, "cancelled")
    with pytest.raises(ConflictError):
        request_cancel(session, job.id, None)


def test_cancel_unknown_job(session: Session) -> None:
    with pytest.raises(NotFoundError):
        request_cancel(session, 12345, None)


def test_mark_interrupted(engine: Engine, session: Session, settings: Settings) -> None:
    running, cancelling, alive, queued = queue_steps(session, settings, 4)
    claim_next(engine, 11)
    claim_next(engine, 12)
    request_cancel(session, cancelling.id, None)
    claim_next(engine, 13)  # `alive` runs on worker 13 ...
    assert mark_interrupted(engine, [11, 12]) == 1  # ... which is alive
    assert reload(engine, running.id).status == JobStatus.interrupted
    assert reload(engine, cancelling.id).status == JobStatus.cancelled  # its cancel stands
    assert reload(engine, alive.id).status == JobStatus.running
    assert mark_interrupted(engine) == 1  # server start: every running job
    assert "server stopped" in reload(engine, alive.id).message
    assert reload(engine, queued.id).status == JobStatus.queued


def test_resume_keeps_id_and_config(engine: Engine, session: Session, settings: Settings) -> None:
    (job,) = queue_steps(session, settings)
    claim_next(engine, 1)
    mark_interrupted(engine)
    resumed = resume(session, job.id, None)
    assert (resumed.id, resumed.status, resumed.config) == (job.id, JobStatus.queued, {"steps": 2})
    assert resumed.finished_at is None and resumed.progress == 0.0
    again = claim_next(engine, 2)
    assert (again.id, again.attempts) == (job.id, 2)
    with pytest.raises(ConflictError, match="only interrupted, failed or cancelled"):
        resume(session, job.id, None)  # running
    finish(engine, job.id, JobStatus.failed, "ValueError: x")
    assert resume(session, job.id, None).status == JobStatus.queued
    claim_next(engine, 3)
    finish(engine, job.id, JobStatus.succeeded, "done")
    with pytest.raises(ConflictError):
        resume(session, job.id, None)
    assert session.exec(select(AuditEvent).where(AuditEvent.action == "job.resume")).all()


def test_requeue_makes_a_new_job(engine: Engine, session: Session, settings: Settings) -> None:
    (job,) = queue_steps(session, settings)
    with pytest.raises(ConflictError, match="still queued"):
        requeue(session, job.id, None, settings)
    claim_next(engine, 1)
    finish(engine, job.id, JobStatus.succeeded, "done", {"x": 1})
    again = requeue(session, job.id, None, settings)
    assert again.id != job.id
    assert (again.kind, again.config, again.status) == ("test:steps", {"steps": 2}, "queued")
    assert reload(engine, job.id).status == JobStatus.succeeded
    with pytest.raises(NotFoundError):
        requeue(session, 999, None, settings)
