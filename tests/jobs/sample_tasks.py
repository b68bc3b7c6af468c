"""Small job kinds for the queue and worker tests; workers load them through
MMSCLEAN_EXTRA_TASK_MODULES=tests.jobs.sample_tasks."""

from __future__ import annotations

import os
import time
from typing import Any

from app.core.errors import ConfigError
from app.jobs.registry import JobContext, task

MODULE = __name__


def _check_steps(config: dict[str, Any], _settings: object) -> None:
    if not isinstance(config.get("steps", 1), int) or config.get("steps", 1) < 1:
        raise ConfigError("config.steps", "must be a positive integer")


@task("test:steps", check=_check_steps)
def steps(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """`steps` progress reports `delay` seconds apart; writes a file into the workdir."""
    n, delay = int(config.get("steps", 5)), float(config.get("delay", 0.1))
    for i in range(n):
        time.sleep(delay)
        context.progress((i + 1) / n, f"step {i + 1} of {n}")
    context.log.info("all %d steps done", n)
    out = context.workdir / "out" / "steps.txt"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(f"{n}\n")
    return {"steps": n, "files": {"steps": str(out)}}


@task("test:fail")
def fail(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    context.progress(0.5, "about to fail")
    raise ValueError("boom\nsecond line of the message")


@task("test:bad-config")
def bad_config(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    raise ConfigError("config.size", "must be positive")


@task("test:crash")
def crash(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """The worker process dies mid-job (as on an OOM kill)."""
    context.progress(0.3, "crashing")
    os._exit(3)


@task("test:silent")
def silent(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """Works without ever reporting progress, so it cannot notice a cancel by itself."""
    context.progress(0.1, "going quiet")
    time.sleep(float(config.get("seconds", 60)))
    return {}
