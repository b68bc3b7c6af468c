"""Guardrail review in the store: slices and their labels, reconstructed models and decisions.

The slices and models are the ones the latest guardrail run left (`app.store.guardrail_runs`
writes them). Label writes and decisions carry the version the client saw; a mismatch raises
`StaleWriteError` with the records as they are now (`app.store.versions` checks, in the write's
transaction). Every user write adds an audit event in its transaction.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np
from pydantic import ConfigDict
from sqlmodel import Session, SQLModel, col, func, select

from app.core.errors import (
    ConfigError,
    ConflictError,
    NotFoundError,
    PermissionDeniedError,
    StaleWriteError,
)
from app.geometry.trajectory import arc_length
from app.store.audit import audit
from app.store.db import commit, write_transaction
from app.store.models import (
    GuardrailKind,
    GuardrailModel,
    GuardrailSlice,
    GuardrailSliceBase,
    ModelStatus,
    Role,
    User,
    utcnow,
)
from app.store.surveys import get_survey, survey_trajectory
from app.store.users import has_role
from app.store.versions import check_versions

MAX_LABELS_PER_WRITE = 5000


# --- public shapes ------------------------------------------------------------------------


class GuardrailSlicePublic(GuardrailSliceBase):
    model_config = ConfigDict(json_schema_serialization_defaults_required=True)  # all answered

    id: int
    version: int
    updated_at: datetime


# The row's columns but the mesh path, a summary of its parameters (computed in `of`) and, on
# request, the parameters whole. It names its fields: a base shared with the table would
# reorder the table's columns.
class GuardrailModelPublic(SQLModel):
    id: int
    survey_id: int
    guardrail_index: int
    kind: GuardrailKind
    status: ModelStatus
    unit_count: int
    icp_residual: float | None
    unit_length: float | None  # metres between poles
    pole_count: int
    slice_count: int
    station_m: tuple[float, float] | None  # first and last slice station, when known
    formats: list[str]  # mesh downloads available
    decided_by: int | None
    decided_at: datetime | None
    version: int
    params: dict[str, Any] | None = None  # the full model, on request

    @classmethod
    def of(cls, row: GuardrailModel, with_params: bool = False) -> GuardrailModelPublic:
        p = row.params or {}
        span = p.get("station_m")
        summary = {
            "unit_length": p.get("unit_length"),
            "pole_count": len(p.get("poles") or []),
            "slice_count": len(p.get("slices") or []),
            "station_m": tuple(span) if span else None,
            "formats": sorted((p.get("files") or {}).keys()),
            "params": dict(p) if with_params else None,
        }
        return cls.model_validate(row, update=summary)


def _current(rows: Sequence[GuardrailSlice]) -> list[dict[str, Any]]:
    return [GuardrailSlicePublic.model_validate(r).model_dump(mode="json") for r in rows]


# --- lookups ------------------------------------------------------------------------------


def get_slice(session: Session, survey_id: int, slice_id: int) -> GuardrailSlice:
    row = session.get(GuardrailSlice, slice_id)
    if row is None or row.survey_id != survey_id:
        raise NotFoundError(f"guardrail slice {slice_id} not found in survey {survey_id}")
    return row


def get_model(session: Session, survey_id: int, model_id: int) -> GuardrailModel:
    row = session.get(GuardrailModel, model_id)
    if row is None or row.survey_id != survey_id:
        raise NotFoundError(f"guardrail model {model_id} not found in survey {survey_id}")
    return row


def _uncertainty():
    """Sort key: most uncertain first (probability nearest 0.5), slices without one last."""
    return (col(GuardrailSlice.probability).is_(None), func.abs(GuardrailSlice.probability - 0.5))


def list_slices(
    session: Session,
    survey_id: int,
    *,
    component: int | None = None,
    label: int | None = None,
    labelled: bool | None = None,
    uncertain_first: bool = False,
    offset: int = 0,
    limit: int = 100,
) -> tuple[int, list[GuardrailSlice]]:
    """(total matching, one page): along the road by default, or most uncertain first."""
    get_survey(session, survey_id)
    where = [GuardrailSlice.survey_id == survey_id]
    if component is not None:
        where.append(GuardrailSlice.component_id == component)
    if label is not None:
        where.append(GuardrailSlice.label == label)
    if labelled is not None:
        human = col(GuardrailSlice.labelled_by)
        where.append(human.is_not(None) if labelled else human.is_(None))
    total = session.exec(select(func.count()).select_from(GuardrailSlice).where(*where)).one()
    order = (GuardrailSlice.component_id, GuardrailSlice.slice_index)
    if uncertain_first:
        order = (*_uncertainty(), GuardrailSlice.id)
    query = select(GuardrailSlice).where(*where).order_by(*order).offset(offset).limit(limit)
    return int(total), list(session.exec(query).all())


def next_uncertain(session: Session, survey_id: int) -> tuple[GuardrailSlice | None, int]:
    """The most uncertain slice no human labelled yet, and how many such slices are left."""
    total, rows = list_slices(session, survey_id, labelled=False, uncertain_first=True, limit=1)
    return (rows[0] if rows else None), total


def trajectory_position(session: Session, survey_id: int, station_m: float) -> list[float] | None:
    """World position of the sensor at `station_m` metres along the survey's frame poses."""
    xyz = survey_trajectory(session, survey_id)
    if not len(xyz):
        return None
    s = arc_length(xyz)
    return [float(np.interp(station_m, s, xyz[:, a])) for a in range(3)]


@dataclass(frozen=True)
class SliceTable:
    """All of a survey's slices as arrays (row order: component, slice index)."""

    id: np.ndarray
    component: np.ndarray
    slice_index: np.ndarray
    predicted: np.ndarray
    label: np.ndarray
    human: np.ndarray  # bool: labelled by a person
    probability: np.ndarray  # float: the classifier's, nan where the run stored none


def slice_table(session: Session, survey_id: int) -> SliceTable:
    cols = (
        GuardrailSlice.id,
        GuardrailSlice.component_id,
        GuardrailSlice.slice_index,
        GuardrailSlice.predicted_label,
        GuardrailSlice.label,
        col(GuardrailSlice.labelled_by).is_not(None),
        GuardrailSlice.probability,
    )
    rows = session.exec(
        select(*cols)
        .where(GuardrailSlice.survey_id == survey_id)
        .order_by(GuardrailSlice.component_id, GuardrailSlice.slice_index)
    ).all()
    a = np.asarray([row[:6] for row in rows], dtype=np.int64).reshape(-1, 6)
    probability = np.array([np.nan if row[6] is None else row[6] for row in rows], dtype=float)
    return SliceTable(
        a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], a[:, 5].astype(bool), probability
    )


def review_slice_rows(session: Session, survey_id: int) -> list[tuple]:
    """(id, component, slice index, label, labelled by a person, version, probability) of every
    slice of the survey, by id: what the viewer's review mode shows and checks writes against."""
    return list(
        session.exec(
            select(
                GuardrailSlice.id,
                GuardrailSlice.component_id,
                GuardrailSlice.slice_index,
                GuardrailSlice.label,
                col(GuardrailSlice.labelled_by).is_not(None),
                GuardrailSlice.version,
                GuardrailSlice.probability,
            )
            .where(GuardrailSlice.survey_id == survey_id)
            .order_by(GuardrailSlice.id)
        ).all()
    )


# --- human writes -------------------------------------------------------------------------


@dataclass(frozen=True)
class SliceLabelEdit:
    id: int
    version: int  # the version the client saw
    label: int  # 0 other, 1 guardrail


def put_slice_labels(
    session: Session, survey_id: int, edits: Sequence[SliceLabelEdit], user: User
) -> list[GuardrailSlice]:
    """Set human labels on many slices in one transaction, all or nothing.

    A slice whose version differs from the one sent raises `StaleWriteError` carrying every
    such slice as it is now; nothing is written then.
    """
    get_survey(session, survey_id)
    if not has_role(user, Role.annotator):
        raise PermissionDeniedError(f"user {user.username!r} may not label slices")
    if not edits:
        raise ConfigError("slices", "give at least one slice")
    if len(edits) > MAX_LABELS_PER_WRITE:
        raise ConfigError("slices", f"at most {MAX_LABELS_PER_WRITE} slices per write")
    ids = [e.id for e in edits]
    twice = next((i for i, n in Counter(ids).items() if n > 1), None)
    if twice is not None:
        raise ConfigError("slices", f"slice {twice} is listed more than once")
    bad = next((e for e in edits if e.label not in (0, 1)), None)
    if bad is not None:
        raise ConfigError("label", f"slice {bad.id}: label must be 0 or 1, not {bad.label}")
    with write_transaction(session):  # the version check and the write: one transaction
        return _put_slice_labels(session, survey_id, edits, ids, user)


def _put_slice_labels(
    session: Session, survey_id: int, edits: Sequence[SliceLabelEdit], ids: list[int], user: User
) -> list[GuardrailSlice]:
    rows = {r.id: r for r in _slices_by_id(session, ids, True) if r.survey_id == survey_id}
    missing = next((i for i in ids if i not in rows), None)
    if missing is not None:
        raise NotFoundError(f"guardrail slice {missing} not found in survey {survey_id}")
    check_versions(
        ids,
        [e.version for e in edits],
        [rows[i].version for i in ids],
        field="slices",
        noun="slice",
        states=lambda stale_ids: _current([rows[int(i)] for i in stale_ids]),
    )
    for e in edits:
        row = rows[e.id]
        before = {"label": row.label, "labelled_by": row.labelled_by}
        row.label = e.label
        row.labelled_by = user.id
        session.add(row)
        audit(
            session, user.id, "guardrail_slice.label", "guardrail_slice", row.id,
            survey_id=survey_id, before=before, after={"label": e.label},
        )  # fmt: skip
    try:
        commit(session)
    except ConflictError as exc:  # lost a race after the check: report what won
        raise StaleWriteError(str(exc), _current(_slices_by_id(session, ids, True))) from exc
    return _slices_by_id(session, ids, fresh=True)


def _slices_by_id(session: Session, ids: Sequence[int], fresh: bool = False) -> list:
    query = select(GuardrailSlice).where(col(GuardrailSlice.id).in_(list(ids)))
    if fresh:
        query = query.execution_options(populate_existing=True)
    by_id = {r.id: r for r in session.exec(query).all()}
    return [by_id[i] for i in ids if i in by_id]


def list_models(session: Session, survey_id: int) -> list[GuardrailModel]:
    get_survey(session, survey_id)
    query = select(GuardrailModel).where(GuardrailModel.survey_id == survey_id)
    return list(session.exec(query.order_by(GuardrailModel.guardrail_index)).all())


def decide_model(
    session: Session,
    survey_id: int,
    model_id: int,
    version: int,
    status: ModelStatus,
    user: User,
) -> GuardrailModel:
    """A reviewer approves or rejects a reconstructed guardrail seen at `version`."""
    get_survey(session, survey_id)
    if not has_role(user, Role.reviewer):
        raise PermissionDeniedError(
            f"user {user.username!r} is {user.role.value}; deciding on models needs a reviewer"
        )
    status = ModelStatus(status)
    if status == ModelStatus.pending:
        raise ConfigError("status", "must be approved or rejected")
    with write_transaction(session):  # the version check and the write: one transaction
        return _decide_model(session, survey_id, model_id, version, status, user)


def _decide_model(
    session: Session,
    survey_id: int,
    model_id: int,
    version: int,
    status: ModelStatus,
    user: User,
) -> GuardrailModel:
    row = get_model(session, survey_id, model_id)
    session.refresh(row)  # as it is now, inside the transaction
    check_versions(
        [model_id],
        [version],
        [row.version],
        field="version",
        noun="guardrail model",
        states=lambda _: GuardrailModelPublic.of(row).model_dump(mode="json"),
    )
    before = row.status.value
    row.status = status
    row.decided_by = user.id
    row.decided_at = utcnow()
    session.add(row)
    audit(
        session, user.id, f"guardrail_model.{'approve' if status == 'approved' else 'reject'}",
        "guardrail_model", row.id, survey_id=survey_id, before=before, after=status.value,
    )  # fmt: skip
    try:
        commit(session)
    except ConflictError as exc:
        now = get_model(session, survey_id, model_id)
        session.refresh(now)
        current = GuardrailModelPublic.of(now).model_dump(mode="json")
        raise StaleWriteError(str(exc), current) from exc
    session.refresh(row)
    return row
