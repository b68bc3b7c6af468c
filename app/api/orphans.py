"""Start-up clean-up of folders no row owns: a server killed during an upload leaves
`surveys_dir/<uuid>/` (the partial upload or archive, up to its whole unpacked size) with no
survey; a job folder may outlive its database. Only server-made names are considered (a
32-hex-digit upload folder in `surveys_dir`, a job-id folder in `jobs_dir`), links are never
followed, and a folder is kept when any job id or any path a row names lies in it or above it.
Surveys imported by path live outside the data dir and are never looked at. Each removal is
logged with its size.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import suppress
from pathlib import Path

from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.api.routes.surveys import UPLOAD_FOLDER
from app.core.settings import Settings
from app.store.owned_files import job_ids, referenced_paths

log = logging.getLogger(__name__)

JOB_FOLDER = re.compile(r"^[0-9]+$")


def folder_size(folder: Path) -> int:
    """Bytes of the files under FOLDER (links counted as links, never followed)."""
    total = 0
    for dirpath, _, filenames in os.walk(folder):
        for name in filenames:
            with suppress(OSError):  # gone meanwhile
                total += os.lstat(os.path.join(dirpath, name)).st_size
    return total


def _candidates(root: Path, pattern: re.Pattern) -> Iterator[Path]:
    if not root.is_dir():
        return
    for entry in root.iterdir():
        if pattern.match(entry.name) and entry.is_dir() and not entry.is_symlink():
            yield entry


def _owned(folder: Path, owned: list[Path]) -> bool:
    return any(p == folder or p.is_relative_to(folder) or folder.is_relative_to(p) for p in owned)


def orphaned_folders(engine: Engine, settings: Settings) -> list[Path]:
    """Upload and job folders that no survey, job or other row owns."""
    with Session(engine) as session:
        jobs, paths = job_ids(session), referenced_paths(session)
    owned = []
    for text in paths:
        try:
            owned.append(Path(text).resolve())
        except (OSError, RuntimeError, ValueError):
            owned.append(Path(os.path.abspath(text)))
    surveys_dir, jobs_dir = settings.surveys_dir.resolve(), settings.jobs_dir.resolve()
    orphans = [f for f in _candidates(surveys_dir, UPLOAD_FOLDER) if not _owned(f, owned)]
    orphans += [
        f
        for f in _candidates(jobs_dir, JOB_FOLDER)
        if int(f.name) not in jobs and not _owned(f, owned)
    ]
    return orphans


def remove_orphans(engine: Engine, settings: Settings) -> list[Path]:
    """Delete the orphaned folders, one log line each with its size; returns them."""
    removed = []
    for folder in orphaned_folders(engine, settings):
        size = folder_size(folder)
        shutil.rmtree(folder, ignore_errors=True)
        if folder.exists():
            log.warning("could not remove the orphaned folder %s (%.1f MB)", folder, size / 2**20)
            continue
        # a warning: it is a crash's leftover, and the server shows warnings without set-up
        log.warning(
            "removed the orphaned folder %s (%.1f MB, no row owns it)", folder, size / 2**20
        )
        removed.append(folder)
    return removed
