"""Survey import in the request: the import route of the API opens and registers a survey at
once, and the `import:survey` job (for drives whose opening takes long) does the same through
this one function."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlmodel import Session

from app.core.errors import InputError, MmscleanError
from app.core.sensors import SensorKind
from app.io import open_survey
from app.io.detect import detect_format
from app.io.point_files import one_line
from app.store.models import Survey
from app.store.surveys import register_opened_survey


def import_source(
    session: Session,
    source: Path,
    fmt: str | None,
    name: str | None,
    user_id: int | None,
    action: str,
    sensor: SensorKind | None = None,
    **payload: Any,
) -> Survey:
    """Open SOURCE with its reader (format detected when not given) and register it with the
    SENSOR kind declared, or (None) as its reader or its point times tell."""
    fmt = fmt or detect_format(source)
    try:
        opened = open_survey(source, fmt)
        if not len(opened):
            raise InputError(source, "holds no frames")
        return register_opened_survey(
            session,
            opened,
            format=fmt,
            source_path=source,
            name=name,
            created_by=user_id,
            action=action,
            sensor=sensor,
            **payload,
        )
    except MmscleanError:
        raise
    except (OSError, ValueError) as exc:
        raise InputError(source, one_line(exc)) from exc
