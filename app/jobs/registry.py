"""What a job kind runs: a task function registered under the kind's name.

A task takes a `JobContext` and the job's config dict and returns a JSON-able result summary
(stored in `Job.result`). By convention the summary has `"files": {name: absolute path}` for
what it wrote (cleaned map, meshes, report) and `"report"` for the report.json path when there
is one. Tasks call `context.progress(fraction, message)` often: it records progress and raises
`JobCancelled` once a user asked to cancel. Task modules register with `@task("kind")`;
`load_tasks()` imports them all (worker processes call it at start), plus the modules named in
`MMSCLEAN_EXTRA_TASK_MODULES` (comma-separated; tests register their own kinds that way).
A task may also register `check=fn(config, settings)`, run when the job is queued, so a bad
config is refused at once (422) instead of failing later in a worker; `model=` the pipeline
whose registry its `config.model_id` names (checked against the store when queued);
`estimate=fn(session, survey_id, config)` the memory its run needs (`app.jobs.memory`), refused
when queued if more than MMSCLEAN_JOB_MEMORY_MB.
"""

from __future__ import annotations

import importlib
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.core.errors import ConfigError
from app.core.settings import Settings
from app.jobs.memory import MemoryEstimate
from app.jobs.task_config import refuse_model_path

TASK_MODULES = (
    "app.jobs.phantom_tasks",
    "app.jobs.clutter_tasks",
    "app.jobs.guardrail_tasks",
    "app.jobs.training_tasks",
    "app.jobs.survey_tasks",
)
EXTRA_TASK_MODULES_ENV = "MMSCLEAN_EXTRA_TASK_MODULES"


class JobCancelled(Exception):  # noqa: N818  (a signal, not an error)
    """Raised inside a task when its job was cancelled; the worker marks it cancelled."""


@dataclass
class JobContext:
    job_id: int
    survey_id: int | None
    user_id: int | None
    engine: Engine  # the worker's own engine
    settings: Settings
    workdir: Path  # settings.jobs_dir / str(job_id), created; outputs go here
    log: logging.Logger  # writes to workdir / "job.log"
    report_progress: Callable[[float, str], bool]  # returns True when cancel was requested

    def progress(self, fraction: float, message: str = "") -> None:
        if self.report_progress(min(max(float(fraction), 0.0), 1.0), message):
            raise JobCancelled(f"job {self.job_id} cancelled")


TaskFn = Callable[[JobContext, dict[str, Any]], dict[str, Any]]
CheckFn = Callable[[dict[str, Any], Settings], None]
EstimateFn = Callable[[Session, int | None, dict[str, Any]], MemoryEstimate]
TASKS: dict[str, TaskFn] = {}
CHECKS: dict[str, CheckFn] = {}
MODELS: dict[str, str] = {}  # kind -> pipeline ("phantom", "guardrail") of its config.model_id
ESTIMATES: dict[str, EstimateFn] = {}


def task(
    kind: str,
    check: CheckFn | None = None,
    model: str | None = None,
    estimate: EstimateFn | None = None,
) -> Callable[[TaskFn], TaskFn]:
    def register(fn: TaskFn) -> TaskFn:
        TASKS[kind] = fn
        if check is not None:
            CHECKS[kind] = check
        if model is not None:
            MODELS[kind] = model
        if estimate is not None:
            ESTIMATES[kind] = estimate
        return fn

    return register


def _module_names() -> tuple[str, ...]:
    extra = os.environ.get(EXTRA_TASK_MODULES_ENV, "")
    return TASK_MODULES + tuple(n.strip() for n in extra.split(",") if n.strip())


def load_tasks() -> dict[str, TaskFn]:
    for name in _module_names():
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:  # a task module that exists but fails to import is a bug
                raise
    return TASKS


def task_for(kind: str) -> TaskFn:
    tasks = load_tasks()
    if kind not in tasks:
        raise ConfigError("kind", f"unknown job kind {kind!r}; known: {', '.join(sorted(tasks))}")
    return tasks[kind]


def check_config(kind: str, config: dict[str, Any], settings: Settings) -> None:
    """Raise the task's ConfigError for a config it would refuse (kinds without a check pass
    only what no kind takes: a checkpoint path)."""
    refuse_model_path(config)
    check = CHECKS.get(kind)
    if check is not None:
        check(config, settings)
