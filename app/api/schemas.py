"""Public shapes of store records shared by several routers (the `Public` variants of
full-stack-fastapi-template): what the API returns, never the password hash.

Every `...Public` is a SQLModel read from its row by attribute (`XPublic.model_validate(row)`),
so no field is copied by hand, and a field the row does not hold is computed in its shape, once.
A shape inherits its table's `XBase` (app.store.models) where the table's column order allows;
the shapes here name their fields instead, since such a base would reorder the table's columns
(the user's password hash, a job's file paths sit between the columns shown).
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import computed_field
from sqlmodel import Field, SQLModel

from app.store.models import JobStatus, Role


class UserPublic(SQLModel):
    id: int
    username: str
    role: Role
    is_active: bool
    created_at: datetime
    version: int


class JobBrief(SQLModel):
    """A job as a survey's summary lists it."""

    id: int
    kind: str
    status: JobStatus
    progress: float = Field(description="0..1")
    message: str
    created_at: datetime
    finished_at: datetime | None


class JobPublic(JobBrief):
    survey_id: int | None
    config: dict[str, Any]
    created_by: int | None
    updated_at: datetime
    started_at: datetime | None
    attempts: int
    cancel_requested: bool
    worker_pid: int | None
    result: dict[str, Any]

    @computed_field(description="run time of the last attempt so far")
    @property
    def seconds(self) -> float | None:
        if self.started_at is None:
            return None
        end = self.finished_at or self.updated_at
        return round(max((end - self.started_at).total_seconds(), 0.0), 3)
