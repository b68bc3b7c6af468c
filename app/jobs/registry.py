"""What a job kind runs: a task function registered under the kind's name.

A task takes a `JobContext` and the job's config dict and returns a JSON-able result summary
(stored in `Job.result`). By convention the summary has `"files": {name: absolute path}` for
what it wrote (cleaned map, meshes, report) and `"report"` for the report.json path when there
is one. Tasks call `context.progress(fraction, message)` often: it records progress and raises
`JobCancelled` once a user asked to cancel. Task modules register with `@task("kind")`;
`load_tasks()` imports them all (worker processes call it at start).
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy.engine import Engine

from app.core.errors import ConfigError
from app.core.settings import Settings

TASK_MODULES = (
    "app.jobs.phantom_tasks",
    "app.jobs.clutter_tasks",
    "app.jobs.guardrail_tasks",
    "app.jobs.training_tasks",
)


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
TASKS: dict[str, TaskFn] = {}


def task(kind: str) -> Callable[[TaskFn], TaskFn]:
    def register(fn: TaskFn) -> TaskFn:
        TASKS[kind] = fn
        return fn

    return register


def load_tasks() -> dict[str, TaskFn]:
    for name in TASK_MODULES:
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
