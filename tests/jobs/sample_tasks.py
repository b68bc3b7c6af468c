"""Small job kinds for the queue and worker tests; workers load them through
MMSCLEAN_EXTRA_TASK_MODULES=tests.jobs.sample_tasks."""

from __future__ import annotations

import ctypes
import os
import signal
import time
from typing import Any

import numpy as np

from app.core.errors import ConfigError
from app.jobs.registry import JobContext, task

MODULE = __name__


def _check_steps(config: dict[str, Any], _settings: object) -> None:
    if not isinstance(config.get("steps", 1), int) or config.get("steps", 1) < 1:
        raise ConfigError("config.steps", "must be a positive integer")


@task("test:steps", check=_check_steps)
def steps(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """`steps` progress reports `delay` seconds apart; writes a file into the workdir (with
    `partial`, a partial one first, as a pipeline writing as it goes)."""
    n, delay = int(config.get("steps", 5)), float(config.get("delay", 0.1))
    if config.get("partial"):
        partial = context.workdir / "out" / "partial.txt"
        partial.parent.mkdir(parents=True, exist_ok=True)
        partial.write_text("half done\n")
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


@task("test:native")
def native(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """A runaway in native code (DUFOMap at a millimetre): it has written a partial file,
    ignores SIGTERM, allocates, then sits in a C call that never reports progress."""
    partial = context.workdir / "out" / "partial.bin"
    partial.parent.mkdir(parents=True, exist_ok=True)
    partial.write_bytes(bytes(1024))
    context.progress(0.1, "into native code")
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    block = np.ones(4 * 1024**2)  # 32 MB
    ctypes.CDLL(None).sleep(int(config.get("seconds", 120)))  # in C: no Python runs meanwhile
    return {"sum": float(block.sum())}


@task("test:silent")
def silent(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """Works without ever reporting progress, so it cannot notice a cancel by itself."""
    context.progress(0.1, "going quiet")
    time.sleep(float(config.get("seconds", 60)))
    return {}
