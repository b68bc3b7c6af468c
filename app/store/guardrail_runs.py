"""What a guardrail run writes to the store, and the run found again.

A guardrail run (the `run:guardrail` job) replaces a survey's slices and models in one
transaction and names the file it saved for rebuilding (`ReconstructionInput`) in its audit
event `guardrail.ingest`, so the stage that produced the current slices is always found with
them (`latest_run`). Human slice labels survive a rerun when the same slice (component, slice
index, about the same station) still exists; after a rebuild, models a reviewer decided on whose
slices did not change keep their decision. A run's slices and models get ids no row of their
table ever had (`fresh_ids`), so a client still holding a replaced one gets 404. The review of
the slices and models a run left is `app.store.guardrail_review`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import sqlalchemy as sa
from sqlmodel import Session, col, select

from app.core.errors import ConflictError
from app.store.audit import audit
from app.store.db import commit
from app.store.guardrail_review import list_models
from app.store.models import (
    AuditEvent,
    GuardrailKind,
    GuardrailModel,
    GuardrailSlice,
    ModelStatus,
    utcnow,
)
from app.store.surveys import get_survey
from app.store.versions import fresh_ids

INGEST_ACTION = "guardrail.ingest"


@dataclass(frozen=True)
class SliceRows:
    """One run's slices as arrays (one entry per slice)."""

    component: np.ndarray
    slice_index: np.ndarray
    station: np.ndarray
    predicted: np.ndarray  # raw classifier label
    probability: np.ndarray
    corrected: np.ndarray  # after adjacency correction

    def __len__(self) -> int:
        return len(self.component)


@dataclass
class ModelRecord:
    """One reconstructed guardrail to store; `slices` are its (component, slice index) keys."""

    kind: GuardrailKind
    mesh_path: str
    params: dict[str, Any]
    unit_count: int
    icp_residual: float | None
    slices: list[tuple[int, int]] = field(default_factory=list)


@dataclass(frozen=True)
class GuardrailRun:
    """The ingest that produced a survey's current slices."""

    event_id: int
    job_id: int | None
    stage_path: str
    config: dict[str, Any]


def latest_run(session: Session, survey_id: int) -> GuardrailRun | None:
    event = session.exec(
        select(AuditEvent)
        .where(AuditEvent.action == INGEST_ACTION, AuditEvent.entity == "survey")
        .where(AuditEvent.entity_id == str(survey_id))
        .order_by(col(AuditEvent.id).desc())
        .limit(1)
    ).first()
    if event is None:
        return None
    p = event.payload
    return GuardrailRun(event.id, p.get("job_id"), p["stage"], dict(p.get("config") or {}))


def _pair_key(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """One int64 per (component, slice index) pair (both well inside +-2**31)."""
    return np.asarray(a, dtype=np.int64) * (1 << 32) + np.asarray(b, dtype=np.int64)


def match_slices(
    component: np.ndarray, slice_index: np.ndarray, in_component: np.ndarray, in_index: np.ndarray
) -> np.ndarray:
    """Position of each (component, slice_index) pair among the `in_*` pairs, -1 if absent."""
    keys = _pair_key(in_component, in_index)
    want = _pair_key(component, slice_index)
    if not len(keys):
        return np.full(len(want), -1, dtype=np.int64)
    order = np.argsort(keys, kind="stable")
    pos = np.clip(np.searchsorted(keys[order], want), 0, len(keys) - 1)
    return np.where(keys[order][pos] == want, order[pos], -1)


def replace_guardrail_run(
    session: Session,
    survey_id: int,
    slices: SliceRows,
    models: Sequence[ModelRecord],
    *,
    stage_path: str,
    config: dict[str, Any],
    job_id: int | None,
    user_id: int | None,
) -> dict[str, int]:
    """Replace the survey's slices and models with a run's, keeping human labels of slices
    that still exist (same component and slice index, station within one slice length)."""
    get_survey(session, survey_id)
    old = session.exec(
        select(
            GuardrailSlice.component_id,
            GuardrailSlice.slice_index,
            GuardrailSlice.station_m,
            GuardrailSlice.label,
            GuardrailSlice.labelled_by,
        ).where(GuardrailSlice.survey_id == survey_id, col(GuardrailSlice.labelled_by).is_not(None))
    ).all()
    label = np.asarray(slices.corrected, dtype=np.int64).copy()
    by = np.full(len(slices), -1, dtype=np.int64)
    kept = 0
    if old:
        o = np.asarray(old, dtype=np.float64)
        at = match_slices(o[:, 0], o[:, 1], slices.component, slices.slice_index)
        spacing = float(config.get("spacing", 0.5))
        ok = at >= 0
        ok[ok] = np.abs(slices.station[at[ok]] - o[ok, 2]) < spacing
        label[at[ok]] = o[ok, 3].astype(np.int64)
        by[at[ok]] = o[ok, 4].astype(np.int64)
        kept = int(ok.sum())
    # ids no row ever had, drawn before the replaced rows go
    first_slice = fresh_ids(session, GuardrailSlice.__table__, len(slices))
    first_model = fresh_ids(session, GuardrailModel.__table__, len(models))
    connection = session.connection()
    connection.execute(sa.delete(GuardrailSlice).where(GuardrailSlice.survey_id == survey_id))
    connection.execute(sa.delete(GuardrailModel).where(GuardrailModel.survey_id == survey_id))
    now = utcnow()
    probability = np.clip(np.asarray(slices.probability, dtype=np.float64), 0.0, 1.0)
    columns = {
        "id": np.arange(first_slice, first_slice + len(slices)),
        "slice_index": slices.slice_index,
        "component_id": slices.component,
        "station_m": slices.station,
        "predicted_label": slices.predicted,
        "probability": probability,
        "corrected_label": slices.corrected,
        "label": label,
    }
    plain = {k: np.asarray(v).tolist() for k, v in columns.items()}  # Python ints and floats
    labelled_by = [None if u < 0 else u for u in by.tolist()]
    fixed = {"survey_id": survey_id, "version": 1, "created_at": now, "updated_at": now}
    rows = [
        {**fixed, **dict(zip(plain, values, strict=True)), "labelled_by": user}
        for *values, user in zip(*plain.values(), labelled_by, strict=True)
    ]
    if rows:
        connection.execute(sa.insert(GuardrailSlice.__table__), rows)
    for index, record in enumerate(models):
        session.add(_model_row(survey_id, index, record, first_model + index))
    audit(
        session, user_id, INGEST_ACTION, "survey", survey_id, job_id=job_id, stage=stage_path,
        config=config, slices=len(slices), human_labels_kept=kept,
        human_labels_dropped=len(old) - kept, models=len(models),
    )  # fmt: skip
    commit(session)
    return {
        "slices": len(slices),
        "human_labels_kept": kept,
        "human_labels_dropped": len(old) - kept,
        "models": len(models),
    }


def _model_row(survey_id: int, index: int, record: ModelRecord, id: int) -> GuardrailModel:
    params = dict(record.params)
    params["slices"] = [[int(c), int(i)] for c, i in record.slices]
    return GuardrailModel(
        id=id,
        survey_id=survey_id,
        guardrail_index=index,
        kind=GuardrailKind(record.kind),
        mesh_path=record.mesh_path,
        params=params,
        unit_count=int(record.unit_count),
        icp_residual=record.icp_residual,
    )


def _same_build(row: GuardrailModel, record: ModelRecord) -> bool:
    """The stored model was built from the same slices with the same point filter."""
    p = row.params or {}
    same_slices = sorted(map(tuple, p.get("slices") or [])) == sorted(record.slices)
    return same_slices and p.get("ground_clearance") == record.params.get("ground_clearance")


def replace_guardrail_models(
    session: Session,
    survey_id: int,
    run: GuardrailRun,
    models: Sequence[ModelRecord],
    *,
    job_id: int | None,
    user_id: int | None,
) -> dict[str, int]:
    """After a rebuild: models a reviewer already decided on whose slices did not change stay
    (with their decision); every other model is replaced by the rebuilt ones (pending)."""
    now_run = latest_run(session, survey_id)
    if now_run is None or now_run.event_id != run.event_id:
        raise ConflictError(
            f"survey {survey_id}: a newer guardrail run replaced the slices during the rebuild; "
            "rebuild again"
        )
    existing = list_models(session, survey_id)
    decided = [r for r in existing if r.status != ModelStatus.pending]
    keep: dict[int, GuardrailModel] = {}
    new: list[ModelRecord] = []
    for record in models:
        same = next((r for r in decided if r.id not in keep and _same_build(r, record)), None)
        if same is None:
            new.append(record)
        else:
            keep[same.id] = same
    gone = [r for r in existing if r.id not in keep]
    first = fresh_ids(session, GuardrailModel.__table__, len(new))
    for r in gone:
        session.delete(r)
    session.flush()  # free the guardrail indices before reusing them
    taken = {r.guardrail_index for r in keep.values()}
    free = (i for i in range(len(existing) + len(models) + 1) if i not in taken)
    for n, record in enumerate(new):
        session.add(_model_row(survey_id, next(free), record, first + n))
    audit(
        session, user_id, "guardrail.rebuild", "survey", survey_id, job_id=job_id,
        run_event=run.event_id, kept=sorted(keep), removed=[r.id for r in gone],
        new=len(new),
    )  # fmt: skip
    commit(session)
    return {
        "models": len(keep) + len(new),
        "kept": len(keep),
        "new": len(new),
        "removed": len(gone),
    }
