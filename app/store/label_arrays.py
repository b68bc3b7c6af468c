"""Every pillar label of a survey as arrays, for a view that shows them all at once: one row of
JSON arrays built by SQLite (no Python object per label), read from the covering index
ix_pillar_label_tile."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from sqlalchemy import text
from sqlmodel import Session

# erased human labels (tombstones) come as "no human label" (-1) with their version, which a
# write over them must send
_ALL_LABELS = text(
    "SELECT json_group_array(cell_id), json_group_array(human), json_group_array(label), "
    "json_group_array(confidence), json_group_array(version) FROM "
    "(SELECT cell_id, source = 'human' AS human, label, coalesce(confidence, -1.0) AS confidence,"
    " version FROM pillar_label WHERE survey_id = :s "
    "UNION ALL SELECT cell_id, 1, -1, -1.0, version FROM pillar_tombstone WHERE survey_id = :s)"
)


@dataclass(frozen=True)
class SurveyLabelArrays:
    cell_ids: np.ndarray  # (L,) int64 store cell ids
    is_human: np.ndarray  # (L,) bool: a human label or erase (else a model pre-label)
    labels: np.ndarray  # (L,) int8 class; -1: an erased human label
    confidence: np.ndarray  # (L,) float32 model confidence; NaN for human labels
    versions: np.ndarray  # (L,) int64


def survey_label_arrays(session: Session, survey_id: int) -> SurveyLabelArrays:
    """All human and model labels of the survey, and its erased human labels."""
    row = session.connection().execute(_ALL_LABELS, {"s": survey_id}).one()
    confidence = np.array(json.loads(row[3]), dtype=np.float32)
    confidence[confidence < 0] = np.nan  # none (human labels): -1 in the query
    return SurveyLabelArrays(
        cell_ids=np.array(json.loads(row[0]), dtype=np.int64),
        is_human=np.array(json.loads(row[1]), dtype=bool),
        labels=np.array(json.loads(row[2]), dtype=np.int8),
        confidence=confidence,
        versions=np.array(json.loads(row[4]), dtype=np.int64),
    )
