"""The worker pool the server owns: `settings.workers` spawned worker processes and a
supervisor thread.

Jobs run in processes, not threads, so a CPU-heavy pipeline never holds the API's GIL. The
supervisor restarts a worker that died (its running job becomes `interrupted`, resumable) and
stops a worker whose job ignores a cancel request (a task in native code that never calls
`progress`: DUFOMap integrating a frame, a big allocation): CANCEL_GRACE_S after the supervisor
first saw the request, the worker gets SIGKILL (native code may ignore SIGTERM), the job's
partial outputs are removed, it ends `cancelled`, and a fresh worker takes the next job. The
grace is counted on the supervisor's own clock from the first sight of the request, not from
the job row's `updated_at`: every later write to the row (a second cancel click) used to
restart it, so a runaway job could outlive any number of cancels.

The pool also owns the tile workers (`app.jobs.cluster`): unless a Dask scheduler is configured,
it starts one local cluster of `settings.workers` processes and gives its address to the job
workers, so every job's tiles share them; it closes the cluster when it stops.

Both start on demand: when the supervisor first sees a queued job, not with the server. Each
process imports torch and the pipelines (about 4 s of CPU); a server that serves labels, review
and exports without running a job never pays for them (and starts in half the time), and the
first job waits those seconds in `queued`. Once started they stay.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from dataclasses import dataclass
from multiprocessing.process import BaseProcess
from pathlib import Path

from dask.distributed import LocalCluster
from sqlalchemy.engine import Engine

from app.core.settings import Settings
from app.jobs.cluster import close_cluster, embedded_cluster
from app.jobs.worker import discard_outputs, worker_main
from app.store.db import make_engine
from app.store.jobs import any_queued, cancel_requests, finish, mark_interrupted
from app.store.models import JobStatus

log = logging.getLogger(__name__)

SUPERVISE_S = 0.5  # how often the supervisor looks at the workers
CANCEL_GRACE_S = 5.0  # a cancelled job still running this long after: its worker is killed
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
        self._cancel_seen: dict[int, float] = {}  # job id -> when the supervisor first saw it
        self._cluster: LocalCluster | None = None  # the embedded tile workers
        self._worker_settings = settings  # what job workers get: with the cluster's address
        self._staffed = False  # the workers were started (for the first queued job)
        self._staff_after = 0.0  # monotonic time of the next try after a failed start
        self._staff_backoff = 0.0

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

    def start(self, on_demand: bool = True) -> WorkerPool:
        """Jobs left running by a previous server -> interrupted; then the supervisor, which
        starts the workers (and the local tile cluster) for the first queued job, or now when
        not `on_demand`."""
        if self._thread is not None:
            raise RuntimeError("the worker pool is already started")
        interrupted = mark_interrupted(self.engine)
        if interrupted:
            log.warning("%d job(s) were running when the server stopped: interrupted", interrupted)
        self.settings.jobs_dir.mkdir(parents=True, exist_ok=True)
        self._stopping.clear()
        if not on_demand:
            with self._lock:
                self._staff()
        self._thread = threading.Thread(
            target=self._supervise, name="mmsclean-job-supervisor", daemon=True
        )
        self._thread.start()
        return self

    def _staff(self) -> None:
        """Start the tile cluster (unless a scheduler is configured) and the job workers; on a
        failure, nothing of them is left running."""
        if self.settings.dask_scheduler is None:
            self._cluster = embedded_cluster(self.settings)
            address = self._cluster.scheduler_address
            self._worker_settings = self.settings.model_copy(update={"dask_scheduler": address})
            log.info(
                "tile workers: %d local processes at %s, Dask dashboard %s (loopback only)",
                self.settings.workers, address, self._cluster.dashboard_link,
            )  # fmt: skip
        slots = [_Slot() for _ in range(self.settings.workers)]
        try:
            for slot in slots:
                self._spawn(slot)
        except Exception:  # no half-staffed pool: the next try starts them all again
            for slot in slots:
                if slot.process is not None and slot.process.is_alive():
                    slot.process.kill()
                    slot.process.join()
            self._close_cluster()
            raise
        self._slots, self._staffed = slots, True
        log.info("started %d job worker(s)", self.settings.workers)

    def _close_cluster(self) -> None:
        """Close the embedded tile cluster, if one runs; job workers get the plain settings."""
        if self._cluster is not None:
            close_cluster(self._cluster)
            self._cluster, self._worker_settings = None, self.settings

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Stop the workers; the jobs they were running become interrupted (resumable)."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        with self._lock:
            processes = [s.process for s in self._slots if s.process is not None]
            self._slots, self._staffed = [], False
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
        self._close_cluster()
        if self._own_engine and self._engine is not None:
            self._engine.dispose()
            self._engine = None

    # --- supervisor ----------------------------------------------------------------------

    def _spawn(self, slot: _Slot) -> None:
        process = self._context.Process(
            target=worker_main,
            args=(self._worker_settings, os.getpid()),
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
                    if not self._staffed:
                        self._staff_when_queued()
                        continue
                    self._replace_dead_workers()
                self._enforce_cancels()
            except Exception:  # the supervisor must outlive a locked database or the like
                log.exception("job supervisor")

    def _staff_when_queued(self) -> None:
        """The workers for the first queued job; a failed start (a cluster that did not come
        up) is logged and tried again with back-off, the job waiting in `queued`."""
        now = time.monotonic()
        if now < self._staff_after or not any_queued(self.engine):
            return
        try:
            self._staff()
        except Exception:
            self._staff_backoff = min(max(2 * self._staff_backoff, 1.0), MAX_BACKOFF_S)
            self._staff_after = now + self._staff_backoff
            log.exception("could not start the job workers; trying again in %.0f s",
                          self._staff_backoff)  # fmt: skip

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
        """Kill the worker of a job still running CANCEL_GRACE_S after its cancel request was
        first seen; remove its partial outputs and end it `cancelled`."""
        with self._lock:
            live = {s.process.pid: s.process for s in self._slots if s.process is not None}
        pending = cancel_requests(self.engine)
        now = time.monotonic()
        asked = {job_id: now for job_id, _, _ in pending}
        self._cancel_seen = {**asked, **{j: t for j, t in self._cancel_seen.items() if j in asked}}
        for job_id, pid, workdir in pending:
            if now - self._cancel_seen[job_id] < CANCEL_GRACE_S or pid not in live:
                continue
            process = live[pid]
            process.kill()  # SIGKILL: native code can neither ignore nor delay it
            process.join()
            jobs_dir = self.settings.jobs_dir.resolve()
            if workdir and Path(workdir).resolve().is_relative_to(jobs_dir):
                discard_outputs(
                    Path(workdir),
                    "cancelled: the task did not stop by itself; its worker was stopped and "
                    "its partial outputs removed",
                )
            finish(
                self.engine,
                job_id,
                JobStatus.cancelled,
                "cancelled (the task did not stop by itself; its worker was stopped)",
            )
            self._cancel_seen.pop(job_id, None)
            log.warning("job %d ignored its cancel request: worker %d killed", job_id, pid)
