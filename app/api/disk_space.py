"""A full disk answers 507, not 500: writes are refused while the data directory's disk has less
than `min_free_mb` free (checked before the write, from a reading at most a second old), and a
write that runs out of space anyway (ENOSPC, SQLite's "database or disk is full") is mapped to
the same answer wherever it is raised. Reads and login keep working; `/health` says `degraded`.

Writes that free space or stop work (DELETE, cancelling a job), logging in and out, and the
read-only POST of the guardrail preview are let through.
"""

from __future__ import annotations

import errno
import shutil
import sqlite3
import threading
import time
from pathlib import Path

from fastapi.requests import HTTPConnection

from app.core.errors import DiskFullError

READING_TTL_S = 1.0
WRITE_METHODS = {"POST", "PUT", "PATCH"}
WORKS_ON_FULL_DISK = {
    ("POST", "/auth/login"),
    ("POST", "/auth/logout"),
    ("POST", "/jobs/{job_id}/cancel"),
    ("POST", "/surveys/{survey_id}/guardrails/slices/preview-correction"),
}


class DiskSpace:
    """Free space of the disk holding FOLDER, read at most once per `READING_TTL_S`."""

    def __init__(self, folder: Path, min_free_mb: float):
        self.folder, self.min_free_mb = Path(folder), float(min_free_mb)
        self._lock = threading.Lock()
        self._read_at, self._free_mb = -float("inf"), float("inf")

    def free_mb(self) -> float:
        with self._lock:
            now = time.monotonic()
            if now - self._read_at >= READING_TTL_S:
                self._free_mb = shutil.disk_usage(_existing(self.folder)).free / 2**20
                self._read_at = now
            return self._free_mb

    def low(self) -> bool:
        return self.free_mb() < self.min_free_mb

    def check(self) -> None:
        """DiskFullError when the free space is below the limit."""
        free = self.free_mb()
        if free < self.min_free_mb:
            raise DiskFullError(free)

    def error(self) -> DiskFullError:
        """The 507 for a write that ran out of space (read afresh)."""
        self._read_at = -float("inf")
        return DiskFullError(self.free_mb())


def _existing(folder: Path) -> Path:
    """FOLDER, or its nearest existing parent (the data dir is made at start-up)."""
    for candidate in (folder, *folder.parents):
        if candidate.exists():
            return candidate
    return Path("/")


def is_disk_full(exc: BaseException) -> bool:
    """Whether EXC (or what it wraps: `__cause__`, `__context__`, SQLAlchemy's `.orig`) is the
    file system or SQLite running out of space."""
    seen: set[int] = set()
    stack: list[BaseException | None] = [exc]
    while stack:
        current = stack.pop()
        if current is None or id(current) in seen:
            continue
        seen.add(id(current))
        if isinstance(current, DiskFullError):
            return True
        if isinstance(current, OSError) and current.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if isinstance(current, sqlite3.Error) and (
            getattr(current, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL
            or "database or disk is full" in str(current)
        ):
            return True
        stack += [current.__cause__, current.__context__, getattr(current, "orig", None)]
    return False


def refuse_writes_on_full_disk(connection: HTTPConnection) -> None:
    """App-wide dependency: a POST / PUT / PATCH is refused (507) while the disk is low."""
    if connection.scope.get("type") != "http":
        return
    method = connection.scope.get("method", "GET")
    route = connection.scope.get("route")
    if method not in WRITE_METHODS or (method, getattr(route, "path", "")) in WORKS_ON_FULL_DISK:
        return
    disk = getattr(connection.app.state, "disk_space", None)
    if disk is not None:
        disk.check()
