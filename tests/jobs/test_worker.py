"""Worker processes and the pool, for real: spawned workers run the test:* kinds of
tests/jobs/sample_tasks.py against an SQLite file."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session

import app.jobs.pool as pool_module
import app.jobs.worker as worker_module
from app.core.settings import Settings
from app.jobs.pool import WorkerPool
from app.jobs.queue import enqueue
from app.jobs.registry import EXTRA_TASK_MODULES_ENV, load_tasks
from app.jobs.worker import ProgressReporter, one_line, run_job
from app.store.db import init_db, make_engine
from app.store.jobs import claim_next, request_cancel, resume
from app.store.models import Job, JobStatus
from tests.jobs.sample_tasks import MODULE as SAMPLE_TASKS

TIMEOUT = 90.0  # a fresh worker imports torch and the pipelines first


def make_settings(data_dir: Path, workers: int) -> Settings:
    return Settings(data_dir=data_dir, sample_dir=None, workers=workers)


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[WorkerPool, Engine]]:
    """Two workers on one database for the whole module."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(EXTRA_TASK_MODULES_ENV, SAMPLE_TASKS)
        settings = make_settings(tmp_path_factory.mktemp("worker") / "var", 2)
        engine = make_engine(settings.database_url)
        init_db(engine)
        pool = WorkerPool(settings, engine).start()
        yield pool, engine
        pool.stop()
        engine.dispose()


def submit(engine: Engine, kind: str, config: dict | None = None) -> int:
    with Session(engine) as session:
        return enqueue(session, kind, config or {}, None, None).id


def job(engine: Engine, job_id: int) -> Job:
    with Session(engine) as session:
        return session.get(Job, job_id)


def wait_for(
    engine: Engine, job_id: int, done: Callable[[Job], bool], timeout: float = TIMEOUT
) -> Job:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        current = job(engine, job_id)
        if done(current):
            return current
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} still {current.status} ({current.message!r})")


def ended(j: Job) -> bool:
    return j.status not in (JobStatus.queued, JobStatus.running)


def test_job_runs_with_progress_log_and_result(running: tuple[WorkerPool, Engine]) -> None:
    _, engine = running
    job_id = submit(engine, "test:steps", {"steps": 12, "delay": 0.15})
    seen: list[float] = []

    def watch(j: Job) -> bool:
        seen.append(j.progress)
        return ended(j)

    done = wait_for(engine, job_id, watch)
    assert done.status == JobStatus.succeeded, done.message
    assert done.progress == 1.0 and done.message.startswith("succeeded in")
    assert any(0 < p < 1 for p in seen) and seen == sorted(seen)  # rose step by step
    assert done.attempts == 1 and done.started_at <= done.finished_at
    workdir = Path(done.result_path)
    assert workdir == Path(running[0].settings.jobs_dir / str(job_id)).resolve()
    assert done.result == {"steps": 12, "files": {"steps": str(workdir / "out" / "steps.txt")}}
    assert (workdir / "out" / "steps.txt").read_text() == "12\n"
    log = Path(done.log_path).read_text()
    assert "attempt 1 of job" in log and "all 12 steps done" in log


def test_failures_end_with_one_line(running: tuple[WorkerPool, Engine]) -> None:
    _, engine = running
    failed = wait_for(engine, submit(engine, "test:fail"), ended)
    assert failed.status == JobStatus.failed
    assert failed.message == "ValueError: boom"
    assert failed.progress == 0.5  # the last report before the failure was kept
    log = Path(failed.log_path).read_text()
    assert "Traceback" in log and "second line of the message" in log
    refused = wait_for(engine, submit(engine, "test:bad-config"), ended)
    assert (refused.status, refused.message) == (JobStatus.failed, "config.size: must be positive")


def only_the_log_is_left(done: Job) -> str:
    """The job folder holds nothing but job.log; its last line."""
    workdir = Path(done.result_path)
    assert [p.name for p in workdir.iterdir()] == ["job.log"]
    return (workdir / "job.log").read_text().splitlines()[-1]


def test_cancel_a_running_job(running: tuple[WorkerPool, Engine]) -> None:
    _, engine = running
    job_id = submit(engine, "test:steps", {"steps": 400, "delay": 0.05, "partial": True})
    wait_for(engine, job_id, lambda j: j.status == JobStatus.running and j.progress > 0)
    with Session(engine) as session:
        request_cancel(session, job_id, None)
    asked = time.monotonic()
    done = wait_for(engine, job_id, ended, timeout=10)
    assert done.status == JobStatus.cancelled and done.progress < 1
    assert time.monotonic() - asked < 3  # honoured at the next progress write
    assert "cancelled after" in only_the_log_is_left(done)  # the partial output is gone


def test_a_runaway_in_native_code_is_cancelled_within_10_s(
    running: tuple[WorkerPool, Engine],
) -> None:
    """The job never reports progress again and ignores SIGTERM; the user asks twice (a second
    request used to restart the grace period): cancelled within 10 s, its partial file gone,
    and a fresh worker runs the next job."""
    pool, engine = running
    job_id = submit(engine, "test:native", {"seconds": 300})
    started = wait_for(engine, job_id, lambda j: j.status == JobStatus.running and j.progress > 0)
    assert (Path(started.result_path) / "out" / "partial.bin").is_file()
    with Session(engine) as session:
        request_cancel(session, job_id, None)
    asked = time.monotonic()
    time.sleep(3)
    with Session(engine) as session:
        request_cancel(session, job_id, None)  # nothing happened yet: the user asks again
    done = wait_for(engine, job_id, ended, timeout=60)
    took = time.monotonic() - asked
    assert done.status == JobStatus.cancelled, done.message
    assert took <= 10, f"cancel took {took:.1f} s"
    assert "partial outputs removed" in only_the_log_is_left(done)
    after = wait_for(engine, submit(engine, "test:steps", {"steps": 2}), ended)
    assert after.status == JobStatus.succeeded and after.worker_pid != started.worker_pid
    assert started.worker_pid not in pool.pids


def test_a_silent_job_is_cancelled_by_stopping_its_worker(
    running: tuple[WorkerPool, Engine], monkeypatch: pytest.MonkeyPatch
) -> None:
    pool, engine = running
    monkeypatch.setattr(pool_module, "CANCEL_GRACE_S", 1.0)
    job_id = submit(engine, "test:silent", {"seconds": 120})
    # Wait for its one progress report: a cancel asked before it is honoured by that write.
    started = wait_for(engine, job_id, lambda j: j.status == JobStatus.running and j.progress > 0)
    with Session(engine) as session:
        request_cancel(session, job_id, None)
    done = wait_for(engine, job_id, ended, timeout=15)
    assert done.status == JobStatus.cancelled
    assert "did not stop by itself" in done.message
    deadline = time.monotonic() + TIMEOUT
    while started.worker_pid in pool.pids or len(pool.pids) < 2:
        assert time.monotonic() < deadline, "the killed worker was not replaced"
        time.sleep(0.1)


def test_a_dead_worker_interrupts_its_job_and_is_replaced(
    running: tuple[WorkerPool, Engine],
) -> None:
    pool, engine = running
    crashed = wait_for(engine, submit(engine, "test:crash"), ended)
    assert crashed.status == JobStatus.interrupted
    assert "died with exit code 3" in crashed.message
    deadline = time.monotonic() + TIMEOUT
    while crashed.worker_pid in pool.pids or len(pool.pids) < 2:
        assert time.monotonic() < deadline, "the dead worker was not replaced"
        time.sleep(0.1)
    after = wait_for(engine, submit(engine, "test:steps", {"steps": 2}), ended)
    assert after.status == JobStatus.succeeded


def one_worker_database(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Settings, Engine]:
    """Settings of one worker and their new database, the sample tasks registered."""
    monkeypatch.setenv(EXTRA_TASK_MODULES_ENV, SAMPLE_TASKS)
    settings = make_settings(tmp_path / "var", 1)
    engine = make_engine(settings.database_url)
    init_db(engine)
    return settings, engine


def test_stop_interrupts_and_a_new_pool_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings, engine = one_worker_database(tmp_path, monkeypatch)
    pool = WorkerPool(settings, engine).start()
    try:
        job_id = submit(engine, "test:steps", {"steps": 100, "delay": 0.05})
        wait_for(engine, job_id, lambda j: j.status == JobStatus.running and j.progress > 0)
    finally:
        pool.stop()
    stopped = job(engine, job_id)
    assert stopped.status == JobStatus.interrupted and "shut down" in stopped.message
    with Session(engine) as session:
        resume(session, job_id, None)
    pool = WorkerPool(settings, engine).start()
    try:
        done = wait_for(engine, job_id, ended)
    finally:
        pool.stop()
    assert (done.status, done.attempts) == (JobStatus.succeeded, 2)
    log = Path(done.log_path).read_text()
    assert "attempt 1 of job" in log and "attempt 2 of job" in log  # appended, not replaced
    engine.dispose()


def test_progress_writes_are_throttled_but_the_last_is_kept(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    writes: list[float] = []

    def fake_report(engine: object, job_id: int, fraction: float, message: str) -> bool:
        writes.append(fraction)
        return fraction > 0.9

    monkeypatch.setattr(worker_module, "report_progress", fake_report)
    reporter = ProgressReporter(None, 1, os.getppid())
    started = time.monotonic()
    stops = [reporter(i / 10_000, "x") for i in range(9_000)]
    elapsed = time.monotonic() - started
    assert len(writes) <= 2 + elapsed / worker_module.PROGRESS_INTERVAL_S
    assert not any(stops)
    reporter.flush()
    assert writes[-1] == 8_999 / 10_000  # the last value reached the store
    assert reporter(1.0, "done") is True  # a final value is written at once; cancel seen
    assert writes[-1] == 1.0


def test_one_line_messages() -> None:
    assert one_line(KeyError("x")) == "KeyError: 'x'"
    assert one_line(RuntimeError("a\nb")) == "RuntimeError: a"
    assert len(one_line(ValueError("v" * 2000))) == worker_module.MAX_MESSAGE


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")  # a zombie is dead, only not yet reaped


def test_workers_start_for_the_first_queued_job(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A pool without work holds no processes; the first queued job starts them (and the
    local tile cluster), and they stay for the next one."""
    settings, engine = one_worker_database(tmp_path, monkeypatch)
    pool = WorkerPool(settings, engine).start()
    try:
        time.sleep(4 * pool_module.SUPERVISE_S)
        assert pool.pids == [] and pool._cluster is None
        first = wait_for(engine, submit(engine, "test:steps", {"steps": 2}), ended)
        assert first.status == JobStatus.succeeded and pool.pids == [first.worker_pid]
        assert pool._cluster is not None  # the tile workers came with the job workers
        second = wait_for(engine, submit(engine, "test:steps", {"steps": 2}), ended)
        assert second.worker_pid == first.worker_pid
    finally:
        pool.stop()
    assert pool.pids == [] and pool._cluster is None


def test_workers_die_with_a_killed_server(tmp_path: Path) -> None:
    """kill -9 of the process that owns the pool takes its workers with it."""
    script = textwrap.dedent(
        f"""
        import sys, time
        from app.core.settings import Settings
        from app.jobs.pool import WorkerPool
        from app.store.db import init_db, make_engine
        settings = Settings(data_dir={str(tmp_path / "var")!r}, sample_dir=None, workers=2)
        engine = make_engine(settings.database_url)
        init_db(engine)
        pool = WorkerPool(settings, engine).start(on_demand=False)
        print(*pool.pids, flush=True)
        time.sleep(600)
        """
    )
    owner = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=Path.cwd()
    )
    try:
        pids = [int(p) for p in owner.stdout.readline().split()]
        assert len(pids) == 2 and all(_alive(p) for p in pids)
        time.sleep(3)  # let the workers get past their start
    finally:
        owner.send_signal(signal.SIGKILL)
        owner.wait()
    deadline = time.monotonic() + 10
    while any(_alive(p) for p in pids):
        assert time.monotonic() < deadline, "workers outlived their server"
        time.sleep(0.1)


def test_a_first_attempt_starts_in_an_empty_folder(tmp_path: Path, monkeypatch) -> None:
    """A job id SQLite hands out again (its job was deleted with its survey) finds the old
    job's folder: the first attempt clears it, so no stale file passes for the new job's."""
    monkeypatch.setenv(EXTRA_TASK_MODULES_ENV, SAMPLE_TASKS)
    settings = make_settings(tmp_path / "var", 1)
    engine = make_engine(settings.database_url)
    init_db(engine)
    with Session(engine) as session:
        job = enqueue(session, "test:steps", {"steps": 1}, None, None, settings)
    stale = settings.jobs_dir / str(job.id) / "cleaned.laz"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"an older job's map")
    claimed = claim_next(engine, os.getpid())
    assert claimed is not None and claimed.attempts == 1
    assert run_job(engine, settings, claimed, load_tasks(), os.getppid()) == JobStatus.succeeded
    assert not stale.exists() and (stale.parent / "job.log").is_file()
    engine.dispose()
