"""A worker process: claims queued jobs one at a time and runs their task.

Pipelines are CPU-heavy; running them here, never in the API process, keeps the API answering.
A worker must not outlive the server that started it (a job whose server is gone would write
into a store the next server already marked it interrupted in), so it asks the kernel to kill
it when its parent dies (Linux `PR_SET_PDEATHSIG`, which also covers kill -9 of the server) and
checks its parent pid while idle and at every progress call.
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import shutil
import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy.engine import Engine

from app.core.errors import ConfigError, MmscleanError
from app.core.settings import Settings
from app.jobs.registry import JobCancelled, JobContext, TaskFn, load_tasks
from app.store.db import make_engine
from app.store.jobs import claim_next, finish, report_progress, set_workdir
from app.store.models import Job, JobStatus

POLL_S = 0.2  # idle: look for a queued job this often
PROGRESS_INTERVAL_S = 0.2  # at most ~5 progress writes per second per job
PR_SET_PDEATHSIG = 1
MAX_MESSAGE = 500
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LOG_NAME = "job.log"


def die_with_parent(parent_pid: int) -> None:
    """Get SIGKILL when the parent dies (Linux); exit now if it already has."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent_pid:
        os._exit(1)


def one_line(exc: BaseException) -> str:
    """The job's failure message: a MmscleanError's own line, else `Type: message`."""
    text = str(exc) if isinstance(exc, MmscleanError) else f"{type(exc).__name__}: {exc}"
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return first if len(first) <= MAX_MESSAGE else first[: MAX_MESSAGE - 3] + "..."


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)  # Path, datetime, ...


def discard_outputs(workdir: Path, note: str) -> int:
    """A cancelled job's partial outputs go: everything in its folder but `job.log`, which
    gets `note` as its last line. Returns how many entries were removed."""
    removed = 0
    if workdir.is_dir():
        for entry in workdir.iterdir():
            if entry.name == LOG_NAME:
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            removed += 1
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        with open(workdir / LOG_NAME, "a", encoding="utf-8") as log:
            log.write(f"{stamp} INFO app.jobs.worker: {note}\n")
    return removed


def json_safe(result: Any) -> dict[str, Any]:
    """A task's result as plain JSON (numpy scalars and paths converted)."""
    if result is None:
        return {}
    if not isinstance(result, dict):
        result = {"value": result}
    return json.loads(json.dumps(result, default=_json_default))


class ProgressReporter:
    """`JobContext.report_progress`: writes at most every PROGRESS_INTERVAL_S (the last value is
    kept and written by `flush`); answers whether the job should stop, as of the last write."""

    def __init__(self, engine: Engine, job_id: int, parent_pid: int):
        self.engine, self.job_id, self.parent_pid = engine, job_id, parent_pid
        self._pending: tuple[float, str] | None = None
        self._last_write = float("-inf")
        self._stop = False

    def __call__(self, fraction: float, message: str) -> bool:
        if os.getppid() != self.parent_pid:
            os._exit(1)  # the server is gone: its successor owns the job now
        self._pending = (fraction, message)
        if time.monotonic() - self._last_write >= PROGRESS_INTERVAL_S or fraction >= 1.0:
            self.flush()
        return self._stop

    def flush(self) -> None:
        if self._pending is not None:
            fraction, message = self._pending
            self._pending = None
            self._stop = report_progress(self.engine, self.job_id, fraction, message)
            self._last_write = time.monotonic()


@contextmanager
def job_logger(job_id: int, path: Path) -> Iterator[logging.Logger]:
    """A logger appending to the job's log; everything `app.*` logs meanwhile goes there too."""
    handler = logging.FileHandler(path, mode="a", encoding="utf-8")
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    package = logging.getLogger("app")
    level = package.level
    package.addHandler(handler)
    package.setLevel(logging.INFO)
    try:
        yield logging.getLogger(f"app.jobs.job{job_id}")
    finally:
        package.removeHandler(handler)
        package.setLevel(level)
        handler.close()


def run_job(
    engine: Engine, settings: Settings, job: Job, tasks: dict[str, TaskFn], parent_pid: int
) -> JobStatus:
    """Run one claimed job to its end state; returns that state."""
    workdir = (settings.jobs_dir / str(job.id)).resolve()
    if job.attempts <= 1 and workdir.exists():
        # a first attempt owns nothing yet: this folder belongs to a job of an earlier
        # database (ids are never reused within one, `unused_id`); its files must not show up
        # as this job's
        shutil.rmtree(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    log_path = workdir / LOG_NAME
    set_workdir(engine, job.id, str(log_path), str(workdir))
    reporter = ProgressReporter(engine, job.id, parent_pid)
    with job_logger(job.id, log_path) as log:
        log.info(
            "attempt %d of job %d (%s) on worker pid %d, config %s",
            job.attempts,
            job.id,
            job.kind,
            os.getpid(),
            json.dumps(job.config),
        )
        context = JobContext(
            job_id=job.id,
            survey_id=job.survey_id,
            user_id=job.created_by,
            engine=engine,
            settings=settings,
            workdir=workdir,
            log=log,
            report_progress=reporter,
        )
        started = time.perf_counter()
        try:
            task = tasks.get(job.kind)
            if task is None:
                raise ConfigError("kind", f"no task for job kind {job.kind!r} in this worker")
            result = json_safe(task(context, dict(job.config)))
        except JobCancelled:
            reporter.flush()
            seconds = time.perf_counter() - started
            discard_outputs(workdir, f"cancelled after {seconds:.1f} s; partial outputs removed")
            finish(engine, job.id, JobStatus.cancelled, "cancelled")
            return JobStatus.cancelled
        except Exception as exc:
            log.exception("failed after %.1f s", time.perf_counter() - started)
            reporter.flush()
            finish(engine, job.id, JobStatus.failed, one_line(exc))
            return JobStatus.failed
        seconds = time.perf_counter() - started
        log.info("succeeded in %.1f s", seconds)
        finish(engine, job.id, JobStatus.succeeded, f"succeeded in {seconds:.1f} s", result)
        return JobStatus.succeeded


def worker_main(settings: Settings, parent_pid: int) -> None:
    """Process entry point (spawned by the pool): claim, run, repeat while the parent lives."""
    die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl+C is the server's to handle
    engine = make_engine(settings.database_url)
    tasks = load_tasks()
    try:
        while os.getppid() == parent_pid:
            job = claim_next(engine, os.getpid())
            if job is None:
                time.sleep(POLL_S)
                continue
            run_job(engine, settings, job, tasks, parent_pid)
    finally:
        engine.dispose()
