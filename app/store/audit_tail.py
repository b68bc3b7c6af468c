"""Following the audit log forward by id: every label and review write leaves its audit row in
the write's own transaction, and SQLite hands ids out in commit order, so the events after an id
are exactly the writes committed since (from any process), read with one index range."""

from __future__ import annotations

import json
from collections.abc import Iterable

import numpy as np
from sqlalchemy import text
from sqlmodel import Session

# the survey: the payload's survey_id (decisions, labels), else the survey the event names (runs)
_NEW_EVENTS = text(
    "SELECT id, action, entity_id, coalesce(json_extract(payload, '$.survey_id'), "
    "CASE WHEN entity = 'survey' THEN entity_id END), json_extract(payload, '$.kind') "
    "FROM audit_event WHERE id > :last "
    "AND action IN (SELECT value FROM json_each(:actions)) ORDER BY id"
)
_BATCH_CELLS = text(
    "SELECT b.survey_id, json_group_array(e.cell_id) FROM pillar_edit AS e "
    "JOIN pillar_edit_batch AS b ON b.id = e.batch_id "
    "WHERE e.batch_id IN (SELECT value FROM json_each(:ids)) GROUP BY b.survey_id"
)

AuditRow = tuple[int, str, str | None, int | str | None, str | None]


def events_after(session: Session, after_id: int, actions: Iterable[str]) -> list[AuditRow]:
    """(id, action, entity id, survey id, payload kind) of the audit events with one of ACTIONS
    after id `after_id`, oldest first; the survey id is the payload's, else the entity's when
    the event names a survey (None otherwise)."""
    query = {"last": after_id, "actions": json.dumps(sorted(set(actions)))}
    return [tuple(row) for row in session.connection().execute(_NEW_EVENTS, query).all()]


def batch_cells(session: Session, batch_ids: list[int]) -> dict[int, np.ndarray]:
    """survey id -> the pillars (store cell ids, with repeats) the edit batches touched."""
    rows = session.connection().execute(_BATCH_CELLS, {"ids": json.dumps(batch_ids)}).all()
    return {int(s): np.array(json.loads(cells), dtype=np.int64) for s, cells in rows}


def newest_audit_id(session: Session) -> int:
    value = session.connection().execute(text("SELECT max(id) FROM audit_event")).scalar()
    return int(value or 0)
