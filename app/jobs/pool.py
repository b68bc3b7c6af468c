"""The worker pool the server owns: `settings.workers` spawned worker processes and a
supervisor thread.

Jobs run in processes, not threads, so a CPU-heavy pipeline never holds the API's GIL. The
supervisor restarts a worker that died (its running job becomes `interrupted`, resumable) and
stops a worker whose job ignores a cancel request (a task that never calls `progress`).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from dataclasses import dataclass
from datetime import timedelta
from multiprocessing.process import BaseProcess

import sqlalchemy as sa
from sqlalchemy.engine import Engine

from app.core.settings import Settings
from app.jobs.queue import finish, mark_interrupted
from app.jobs.worker import worker_main
from app.store.db import make_engine
from app.store.models import Job, JobStatus, utcnow

log = logging.getLogger(__name__)

SUPERVISE_S = 0.5  # how often the supervisor looks at the workers
CANCEL_GRACE_S = 10.0  # a cancelled job still silent after this long: its worker is killed
QUICK_DEATH_S = 10.0  # a worker dying this soon after its start is restarted with back-off
MAX_BACKOFF_S = 60.0
STOP_TIMEOUT_S = 10.0


@dataclass
class _Slot:
    process: BaseProcess | None = None
    started: float = 0.0
    backoff: float = 0.0
    next_start: float = 0.0


class WorkerPool:
    def __init__(self, settings: Settings, engine: Engine | None = None):
        self.settings = settings
        self._engine = engine
        self._own_engine = engine is None
        self._context = multiprocessing.get_context("spawn")
        self._slots: list[_Slot] = []
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def engine(self) -> Engine:
        if self._engine is None:
            self._engine = make_engine(self.settings.database_url)
        return self._engine

    @property
    def pids(self) -> list[int]:
        """Process ids of the live workers."""
        with self._lock:
            return [s.process.pid for s in self._slots if s.process and s.process.is_alive()]

    def start(self) -> WorkerPool:
        """Jobs left running by a previous server -> interrupted; then start the workers."""
        if self._thread is not None:
            raise RuntimeError("the worker pool is already started")
        interrupted = mark_interrupted(self.engine)
        if interrupted:
            log.warning("%d job(s) were running when the server stopped: interrupted", interrupted)
        self.settings.jobs_dir.mkdir(parents=True, exist_ok=True)
        self._stopping.clear()
        with self._lock:
            self._slots = [_Slot() for _ in range(self.settings.workers)]
            for slot in self._slots:
                self._spawn(slot)
        self._thread = threading.Thread(
            target=self._supervise, name="mmsclean-job-supervisor", daemon=True
        )
        self._thread.start()
        log.info("started %d job worker(s)", self.settings.workers)
        return self

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Stop the workers; the jobs they were running become interrupted (resumable)."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        with self._lock:
            processes = [s.process for s in self._slots if s.process is not None]
            self._slots = []
        for process in processes:
            if process.is_alive():
                process.terminate()
        deadline = time.monotonic() + timeout
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.kill()
                process.join()
        if processes:
            stopped = mark_interrupted(
                self.engine,
                [p.pid for p in processes],
                "interrupted: the server shut down while it ran; resume it to run it again",
            )
            if stopped:
                log.warning("%d running job(s) interrupted by the shutdown", stopped)
        if self._own_engine and self._engine is not None:
            self._engine.dispose()
            self._engine = None

    # --- supervisor ----------------------------------------------------------------------

    def _spawn(self, slot: _Slot) -> None:
        process = self._context.Process(
            target=worker_main,
            args=(self.settings, os.getpid()),
            name="mmsclean-job-worker",
        )
        process.start()
        slot.process, slot.started = process, time.monotonic()

    def _supervise(self) -> None:
        while not self._stopping.wait(SUPERVISE_S):
            try:
                with self._lock:
                    if self._stopping.is_set():
                        return
                    self._replace_dead_workers()
                self._enforce_cancels()
            except Exception:  # the supervisor must outlive a locked database or the like
                log.exception("job supervisor")

    def _replace_dead_workers(self) -> None:
        now = time.monotonic()
        for slot in self._slots:
            process = slot.process
            if process is not None and not process.is_alive():
                process.join()
                lost = mark_interrupted(
                    self.engine,
                    [process.pid],
                    f"interrupted: its worker (pid {process.pid}) died with exit code "
                    f"{process.exitcode}; resume it to run it again",
                )
                log.warning(
                    "job worker %d died (exit code %s, %d job(s) interrupted); restarting it",
                    process.pid,
                    process.exitcode,
                    lost,
                )
                quick = now - slot.started < QUICK_DEATH_S
                slot.backoff = min(max(2 * slot.backoff, 1.0), MAX_BACKOFF_S) if quick else 0.0
                slot.process, slot.next_start = None, now + slot.backoff
            if slot.process is None and now >= slot.next_start:
                self._spawn(slot)

    def _enforce_cancels(self) -> None:
        """Kill the worker of a job asked to cancel that has not written progress since."""
        with self._lock:
            live = {s.process.pid: s.process for s in self._slots if s.process is not None}
        if not live:
            return
        cutoff = utcnow() - timedelta(seconds=CANCEL_GRACE_S)
        with self.engine.connect() as conn:
            stuck = conn.execute(
                sa.select(Job.id, Job.worker_pid).where(
                    Job.status == JobStatus.running,
                    Job.cancel_requested,
                    Job.updated_at < cutoff,
                    Job.worker_pid.in_(list(live)),
                )
            ).all()
        for job_id, pid in stuck:
            process = live[pid]
            process.kill()
            process.join()
            finish(
                self.engine,
                job_id,
                JobStatus.cancelled,
                "cancelled (the task did not stop by itself; its worker was stopped)",
            )
            log.warning("job %d ignored its cancel request: worker %d killed", job_id, pid)
