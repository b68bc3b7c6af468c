"""The CNN's pillar classes as model pre-labels: a survey keeps only its newest ones, replaced in
the one transaction that writes the new, so a reader never sees half of each (bulk SQL: a run
writes hundreds of thousands of rows)."""

from __future__ import annotations

import itertools

import numpy as np
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.store.audit import audit
from app.store.models import LabelSource, utcnow

_INSERT_MODEL_LABELS = (
    "INSERT INTO pillar_label (survey_id, cell_id, label, source, confidence, user_id, "
    "model_version_id, version, created_at, updated_at) VALUES (?, ?, ?, ?, ?, NULL, ?, 1, ?, ?)"
)
_DELETE_MODEL_LABELS = "DELETE FROM pillar_label WHERE survey_id = ? AND source = ?"


def store_model_labels(
    engine: Engine,
    survey_id: int,
    cells: np.ndarray,
    labels: np.ndarray,
    confidence: np.ndarray,
    model_version_id: int,
    user_id: int | None,
    job_id: int,
) -> int:
    """Replace the survey's model pre-labels in one transaction; returns how many were written."""
    now = utcnow().replace(tzinfo=None).isoformat(sep=" ", timespec="microseconds")
    model = LabelSource.model.value
    rows = zip(
        itertools.repeat(survey_id),
        cells.tolist(),
        labels.tolist(),
        itertools.repeat(model),
        confidence.tolist(),
        itertools.repeat(model_version_id),
        itertools.repeat(now),
        itertools.repeat(now),
    )
    with Session(engine) as session:
        conn = session.connection()
        conn.exec_driver_sql(_DELETE_MODEL_LABELS, (survey_id, model))
        if len(cells):
            conn.exec_driver_sql(_INSERT_MODEL_LABELS, list(rows))
        audit(
            session,
            user_id,
            "pillar.model_labels",
            "survey",
            survey_id,
            job_id=job_id,
            model_version_id=model_version_id,
            pillars=len(cells),
            per_class=np.bincount(labels, minlength=4).tolist(),
        )
        session.commit()
    return len(cells)
