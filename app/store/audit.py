"""The audit trail: every write a user makes is recorded in the same transaction as the write."""

from __future__ import annotations

from typing import Any

import sqlalchemy as sa
from sqlmodel import Session, SQLModel

from app.store.models import AuditEvent


def audit(
    session: Session,
    user_id: int | None,
    action: str,
    entity: str,
    entity_id: object | None = None,
    **payload: Any,
) -> None:
    """Add an AuditEvent to `session` (committed or rolled back with the write it describes)."""
    session.add(
        AuditEvent(
            user_id=user_id,
            action=action,
            entity=entity,
            entity_id=None if entity_id is None else str(entity_id),
            payload=payload,
        )
    )


def unused_id(model: type[SQLModel], entity: str) -> sa.ColumnElement[int]:
    """SQL for a new id of `model` that no live row and no audit event of `entity` has used.

    The tables have no AUTOINCREMENT (rebuilding them would cascade into their children), so
    SQLite hands the highest id out again after that row's deletion: a survey registered after
    the newest one was deleted would inherit its audit history, a job its events. Assign it to
    the new record's id: it is evaluated inside the INSERT, so two writers cannot draw one id.
    """
    live = sa.func.coalesce(
        sa.select(sa.func.max(model.id)).scalar_subquery(),  # type: ignore[attr-defined]
        0,
    )
    audited = sa.func.coalesce(
        sa.select(sa.func.max(sa.cast(AuditEvent.entity_id, sa.Integer)))
        .where(AuditEvent.entity == entity)
        .scalar_subquery(),
        0,
    )
    return sa.case((live >= audited, live), else_=audited) + 1
