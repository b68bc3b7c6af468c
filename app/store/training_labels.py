"""The human labels retraining learns from, as arrays per survey: pillar labels, and where
known whether each labelled pillar holds points (a survey's model pre-labels cover exactly the
pillars its last phantom run found points in, so a human label with no model label beside it,
on a survey that has model labels, lies where that run saw nothing to learn from); and the
guardrail slices people labelled."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from sqlalchemy import text
from sqlmodel import Session

_MAPPED = (
    "EXISTS (SELECT 1 FROM pillar_label AS m WHERE m.survey_id = h.survey_id "
    "AND m.cell_id = h.cell_id AND m.source = 'model')"
)
_HUMAN = (
    "SELECT h.survey_id, json_group_array(h.cell_id), json_group_array(h.label), "
    "json_group_array({mapped}) FROM pillar_label AS h WHERE h.source = 'human' "
    "GROUP BY h.survey_id"
)
_HAS_MODEL_LABELS = text(
    "SELECT EXISTS (SELECT 1 FROM pillar_label WHERE survey_id = :s AND source = 'model')"
)


@dataclass(frozen=True)
class SurveyLabels:
    cells: np.ndarray  # (L,) int64 packed pillar ids (STORE_GRID)
    classes: np.ndarray  # (L,) int64 PillarClass
    mapped: np.ndarray | None  # (L,) bool: a phantom run found points there; None: unknown


def human_pillar_labels(
    session: Session, survey_ids: list[int] | None = None, with_mapped: bool = False
) -> dict[int, SurveyLabels]:
    """survey id -> its human pillar labels (of SURVEY_IDS, or every survey); `mapped` only
    when asked for and the survey has model pre-labels. The rows are built into JSON arrays by
    SQLite (one row per survey, no Python object per label)."""
    out = {}
    conn = session.connection()
    query = text(_HUMAN.format(mapped=_MAPPED if with_mapped else "0"))
    for survey, cells, classes, flags in conn.execute(query).all():
        if survey_ids is not None and survey not in survey_ids:
            continue
        has_model = with_mapped and conn.execute(_HAS_MODEL_LABELS, {"s": survey}).scalar()
        out[int(survey)] = SurveyLabels(
            np.array(json.loads(cells), dtype=np.int64),
            np.array(json.loads(classes), dtype=np.int64),
            np.array(json.loads(flags), dtype=bool) if has_model else None,
        )
    return out


def reviewed_slices(session: Session, survey_ids: list[int] | None) -> dict[int, np.ndarray]:
    """survey id -> (S, 4) float64 [component, slice index, station, label] of the slices a
    person labelled."""
    rows = (
        session.connection()
        .execute(
            text(
                "SELECT survey_id, component_id, slice_index, station_m, label "
                "FROM guardrail_slice WHERE labelled_by IS NOT NULL"
            )
        )
        .all()
    )
    by_survey: dict[int, list] = {}
    for survey, *rest in rows:
        if survey_ids is None or survey in survey_ids:
            by_survey.setdefault(int(survey), []).append(rest)
    return {s: np.array(r, dtype=np.float64) for s, r in by_survey.items()}
