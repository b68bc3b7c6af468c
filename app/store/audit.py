"""The audit trail: every write a user makes is recorded in the same transaction as the write."""

from __future__ import annotations

from typing import Any

from sqlmodel import Session

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
