"""Clutter review: the instances a clutter run found, and the reviewers' decisions on them.

A `run:clutter` job replaces a survey's instances in one transaction (`replace_instances`),
each with a pending decision. Reviewers then approve (remove the instance's points), reject
(keep them) or reset to pending (the pipeline's own decision), one or many at once in one
transaction (`decide`). Each decision carries the version the client saw; any stale one rejects
the whole request with the current state of the stale decisions (`StaleWriteError`, 409), so
two reviewers never overwrite each other unseen (`app.store.versions` checks, in the write's
transaction). A run's instances get ids no instance ever had (`fresh_ids`): a reviewer still
holding an instance of the previous run at version 1 gets 404, never a decision on a new
instance that happens to be at version 1 too. Writes are plain SQL executemany through the
tables' own column types: a run's thousands of instances, or a reviewer's "approve all on this
frame", are one statement each, not one ORM object per row.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlmodel import Session, col, select

from app.core.errors import ConfigError, ConflictError, NotFoundError, StaleWriteError
from app.store.db import commit, write_transaction
from app.store.models import (
    AuditEvent,
    ClutterDecision,
    ClutterInstance,
    Decision,
    Frame,
    Job,
    JobStatus,
    utcnow,
)
from app.store.versions import check_versions, fresh_ids

RUN_KIND = "run:clutter"
RECOMPUTE_KIND = "clutter:recompute"
MAX_PAGE = 1000

_INSTANCE = ClutterInstance.__table__
_DECISION = ClutterDecision.__table__
_AUDIT = AuditEvent.__table__
_FRAME = Frame.__table__

ACTIONS = {
    Decision.approved: "clutter.approve",
    Decision.rejected: "clutter.reject",
    Decision.pending: "clutter.reset",
}


@dataclass(frozen=True)
class InstanceState:
    """One instance with its decision (what lists and the 409 answer show)."""

    id: int
    survey_id: int
    frame_id: str
    instance_index: int
    class_name: str
    point_count: int
    mask_path: str | None
    bbox: list[int] | None
    moving: bool | None
    track_id: int | None
    decision: Decision
    version: int
    user_id: int | None
    decided_at: datetime | None

    def current(self) -> dict[str, Any]:
        """The decision as it is now, JSON-ready (the `current` of a 409)."""
        return {
            "instance_id": self.id,
            "decision": self.decision.value,
            "version": self.version,
            "user_id": self.user_id,
            "decided_at": None if self.decided_at is None else self.decided_at.isoformat(),
        }


@dataclass(frozen=True)
class DecisionWrite:
    """A reviewer's verdict on one instance, given the decision version they saw."""

    instance_id: int
    version: int
    decision: Decision


@dataclass(frozen=True)
class FrameCount:
    frame_id: str
    instances: int
    pending: int


def _state_query() -> sa.Select:
    return (
        sa.select(
            _INSTANCE.c.id,
            _INSTANCE.c.survey_id,
            _INSTANCE.c.frame_id,
            _INSTANCE.c.instance_index,
            _INSTANCE.c.class_name,
            _INSTANCE.c.point_count,
            _INSTANCE.c.mask_path,
            _INSTANCE.c.bbox,
            _INSTANCE.c.moving,
            _INSTANCE.c.track_id,
            _DECISION.c.decision,
            _DECISION.c.version,
            _DECISION.c.user_id,
            _DECISION.c.decided_at,
        )
        .select_from(_INSTANCE)
        .join(_DECISION, _DECISION.c.instance_id == _INSTANCE.c.id)
    )


def _state(row: sa.Row) -> InstanceState:
    return InstanceState(**row._mapping)


def _filters(
    survey_id: int, frame_id: str | None, decision: Decision | None, class_name: str | None
) -> list[sa.ColumnElement[bool]]:
    where = [_INSTANCE.c.survey_id == survey_id]
    if frame_id is not None:
        where.append(_INSTANCE.c.frame_id == frame_id)
    if decision is not None:
        where.append(_DECISION.c.decision == Decision(decision))
    if class_name is not None:
        where.append(_INSTANCE.c.class_name == class_name)
    return where


def list_instances(
    session: Session,
    survey_id: int,
    frame_id: str | None = None,
    decision: Decision | None = None,
    class_name: str | None = None,
    offset: int = 0,
    limit: int = 100,
) -> tuple[int, list[InstanceState]]:
    """(total matching, one page) of a survey's instances in frame order, then instance index."""
    if offset < 0:
        raise ConfigError("offset", f"must be 0 or more, got {offset}")
    if not 1 <= limit <= MAX_PAGE:
        raise ConfigError("limit", f"must be 1-{MAX_PAGE}, got {limit}")
    where = _filters(survey_id, frame_id, decision, class_name)
    conn = session.connection()
    total = conn.execute(
        sa.select(sa.func.count())
        .select_from(_INSTANCE)
        .join(_DECISION, _DECISION.c.instance_id == _INSTANCE.c.id)
        .where(*where)
    ).scalar_one()
    frame_order = (
        sa.select(_FRAME.c.frame_index)
        .where(_FRAME.c.survey_id == survey_id, _FRAME.c.frame_id == _INSTANCE.c.frame_id)
        .scalar_subquery()
    )
    rows = conn.execute(
        _state_query()
        .where(*where)
        .order_by(frame_order, _INSTANCE.c.frame_id, _INSTANCE.c.instance_index)
        .offset(offset)
        .limit(limit)
    ).all()
    return int(total), [_state(r) for r in rows]


def get_instance(session: Session, survey_id: int, instance_id: int) -> InstanceState:
    """One instance of the survey; an id of another survey is not found, as an unknown one."""
    row = (
        session.connection()
        .execute(
            _state_query().where(_INSTANCE.c.id == instance_id, _INSTANCE.c.survey_id == survey_id)
        )
        .first()
    )
    if row is None:
        raise NotFoundError(f"clutter instance {instance_id} not found in survey {survey_id}")
    return _state(row)


def frame_counts(session: Session, survey_id: int) -> list[FrameCount]:
    """Every frame of the survey (frame order) with its instances and how many are pending;
    frames the store does not list but instances name come last."""
    conn = session.connection()
    counts = {
        r.frame_id: (int(r.instances), int(r.pending or 0))
        for r in conn.execute(
            sa.select(
                _INSTANCE.c.frame_id,
                sa.func.count().label("instances"),
                sa.func.sum(sa.case((_DECISION.c.decision == Decision.pending, 1), else_=0)).label(
                    "pending"
                ),
            )
            .select_from(_INSTANCE)
            .join(_DECISION, _DECISION.c.instance_id == _INSTANCE.c.id)
            .where(_INSTANCE.c.survey_id == survey_id)
            .group_by(_INSTANCE.c.frame_id)
        )
    }
    frames = conn.execute(
        sa.select(_FRAME.c.frame_id)
        .where(_FRAME.c.survey_id == survey_id)
        .order_by(_FRAME.c.frame_index)
    ).scalars()
    out = [FrameCount(f, *counts.pop(f, (0, 0))) for f in frames]
    out += [FrameCount(f, *c) for f, c in sorted(counts.items())]
    return out


def decide(
    session: Session, survey_id: int, writes: Sequence[DecisionWrite], user_id: int | None
) -> list[InstanceState]:
    """Apply the decisions in one transaction (commits) and audit each; returns the new states
    in request order. Unknown ids (or ids of another survey) -> NotFoundError; any stale
    version -> StaleWriteError with the current state of every stale decision, nothing written.
    """
    if not writes:
        return []
    ids = [int(w.instance_id) for w in writes]
    seen: set[int] = set()
    for i, instance_id in enumerate(ids):
        if instance_id in seen:
            raise ConfigError(f"decisions[{i}].instance_id", f"instance {instance_id} is twice")
        seen.add(instance_id)
    with write_transaction(session):  # the version check and the update: one transaction
        return _decide(session, survey_id, writes, ids, user_id)


def _decide(
    session: Session,
    survey_id: int,
    writes: Sequence[DecisionWrite],
    ids: list[int],
    user_id: int | None,
) -> list[InstanceState]:
    before = _states(session, survey_id, ids)
    missing = [i for i in ids if i not in before]
    if missing:
        shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
        raise NotFoundError(f"clutter instance(s) {shown} not found in survey {survey_id}")
    check_versions(
        ids,
        [w.version for w in writes],
        [before[i].version for i in ids],
        field="decisions",
        noun="clutter instance",
        states=lambda stale_ids: [before[int(i)].current() for i in stale_ids],
    )
    now = utcnow()
    conn = session.connection()
    result = conn.execute(
        sa.update(_DECISION)
        .where(
            _DECISION.c.instance_id == sa.bindparam("w_instance"),
            _DECISION.c.version == sa.bindparam("w_version"),
        )
        .values(
            decision=sa.bindparam("w_decision"),
            user_id=sa.bindparam("w_user"),
            decided_at=sa.bindparam("w_at"),
            updated_at=now,
            version=_DECISION.c.version + 1,
        ),
        [
            {
                "w_instance": w.instance_id,
                "w_version": w.version,
                "w_decision": Decision(w.decision),
                "w_user": None if w.decision == Decision.pending else user_id,
                "w_at": None if w.decision == Decision.pending else now,
            }
            for w in writes
        ],
    )
    after = _states(session, survey_id, ids)
    applied = all(
        w.instance_id in after and after[w.instance_id].version == w.version + 1 for w in writes
    )
    if conn.dialect.supports_sane_multi_rowcount:
        applied &= result.rowcount == len(writes)
    if not applied:  # another writer got in between the check and the update: undo all
        session.rollback()
        now_states = _states(session, survey_id, ids)
        raise StaleWriteError(
            "clutter decisions were changed by someone else meanwhile; reload and retry",
            current=[
                now_states[w.instance_id].current()
                for w in writes
                if w.instance_id in now_states and now_states[w.instance_id].version != w.version
            ],
        )
    conn.execute(
        sa.insert(_AUDIT),
        [
            {
                "at": now,
                "user_id": user_id,
                "action": ACTIONS[Decision(w.decision)],
                "entity": "clutter_instance",
                "entity_id": str(w.instance_id),
                "payload": {
                    "survey_id": survey_id,
                    "frame_id": before[w.instance_id].frame_id,
                    "instance_index": before[w.instance_id].instance_index,
                    "before": before[w.instance_id].decision.value,
                    "after": Decision(w.decision).value,
                    "version": w.version + 1,
                },
            }
            for w in writes
        ],
    )
    commit(session)
    return [after[i] for i in ids]


def _states(session: Session, survey_id: int, ids: list[int]) -> dict[int, InstanceState]:
    rows = (
        session.connection()
        .execute(
            _state_query().where(
                _INSTANCE.c.survey_id == survey_id,
                _INSTANCE.c.id.in_(
                    sa.select(sa.column("value", sa.Integer)).select_from(
                        sa.func.json_each(sa.literal(ids, sa.JSON))
                    )
                ),
            )
        )
        .all()
    )
    return {int(r.id): _state(r) for r in rows}


def replace_instances(
    session: Session,
    survey_id: int,
    instances: Sequence[dict[str, Any]],
    user_id: int | None,
    job_id: int | None = None,
) -> int:
    """Replace the survey's instances (and their decisions) by `instances`, each pending, in
    one transaction (commits); rows are ClutterInstance columns (frame_id, instance_index,
    class_name, point_count, mask_path, bbox, moving, track_id). Returns how many."""
    now = utcnow()
    conn = session.connection()
    first = fresh_ids(session, _INSTANCE, len(instances))  # before the replaced rows go
    replaced = conn.execute(
        sa.select(sa.func.count()).where(_INSTANCE.c.survey_id == survey_id)
    ).scalar_one()
    conn.execute(sa.delete(_INSTANCE).where(_INSTANCE.c.survey_id == survey_id))  # cascades
    if instances:
        conn.execute(
            sa.insert(_INSTANCE),
            [
                {**row, "id": first + n, "survey_id": survey_id, "created_at": now}
                for n, row in enumerate(instances)
            ],
        )
        conn.execute(
            sa.insert(_DECISION).from_select(
                ["instance_id", "decision", "version", "created_at", "updated_at"],
                sa.select(
                    _INSTANCE.c.id,
                    sa.literal(Decision.pending.value),
                    sa.literal(1),
                    sa.literal(now, ClutterDecision.__table__.c.created_at.type),
                    sa.literal(now, ClutterDecision.__table__.c.updated_at.type),
                ).where(_INSTANCE.c.survey_id == survey_id),
            )
        )
    conn.execute(
        sa.insert(_AUDIT),
        [
            {
                "at": now,
                "user_id": user_id,
                "action": "clutter.ingest",
                "entity": "survey",
                "entity_id": str(survey_id),
                "payload": {"job_id": job_id, "instances": len(instances), "replaced": replaced},
            }
        ],
    )
    commit(session)
    return len(instances)


def review_decisions(session: Session, survey_id: int) -> list[tuple[str, int, Decision, str]]:
    """(frame_id, instance_index, decision, mask_path) of every instance of the survey."""
    rows = session.connection().execute(
        sa.select(
            _INSTANCE.c.frame_id,
            _INSTANCE.c.instance_index,
            _DECISION.c.decision,
            _INSTANCE.c.mask_path,
        )
        .select_from(_INSTANCE)
        .join(_DECISION, _DECISION.c.instance_id == _INSTANCE.c.id)
        .where(_INSTANCE.c.survey_id == survey_id)
    )
    return [(r[0], int(r[1]), Decision(r[2]), r[3]) for r in rows]


@dataclass(frozen=True)
class InstanceClass:
    """What an export needs of one instance: where it is, what the run called it, the verdict."""

    frame_id: str
    instance_index: int
    class_name: str
    moving: bool | None
    track_id: int | None
    decision: Decision
    mask_path: str | None


def instance_classes(session: Session, survey_id: int) -> list[InstanceClass]:
    """Every instance of the survey with its class, motion, track and decision, in the order the
    run stored them."""
    rows = session.connection().execute(
        sa.select(
            _INSTANCE.c.frame_id,
            _INSTANCE.c.instance_index,
            _INSTANCE.c.class_name,
            _INSTANCE.c.moving,
            _INSTANCE.c.track_id,
            _DECISION.c.decision,
            _INSTANCE.c.mask_path,
        )
        .select_from(_INSTANCE)
        .join(_DECISION, _DECISION.c.instance_id == _INSTANCE.c.id)
        .where(_INSTANCE.c.survey_id == survey_id)
        .order_by(_INSTANCE.c.id)  # the run's order: frame by frame
    )
    return [InstanceClass(r[0], int(r[1]), r[2], r[3], r[4], Decision(r[5]), r[6]) for r in rows]


def latest_run(session: Session, survey_id: int) -> Job | None:
    """The survey's newest succeeded clutter run (its folder holds the review membership)."""
    return session.exec(
        select(Job)
        .where(Job.survey_id == survey_id, Job.kind == RUN_KIND, Job.status == JobStatus.succeeded)
        .order_by(col(Job.finished_at).desc(), col(Job.id).desc())
    ).first()


def run_folder_of(mask_paths: Sequence[str | None]) -> Path | None:
    """The run folder the instances' mask images lie in (`<run>/instances/<frame>/<i>.png`);
    None when there is no mask path. Instances from two runs cannot coexist (a run replaces
    them all), so one folder is expected; more is an inconsistent store."""
    folders = {Path(p).parent.parent.parent for p in mask_paths if p}
    if len(folders) > 1:
        raise ConflictError(f"the survey's clutter instances come from {len(folders)} runs")
    return folders.pop() if folders else None


def has_review(session: Session, survey_id: int) -> bool:
    """The survey has instances, or at least a finished clutter run (possibly with none)."""
    first = session.connection().execute(
        sa.select(_INSTANCE.c.id).where(_INSTANCE.c.survey_id == survey_id).limit(1)
    )
    return first.first() is not None or latest_run(session, survey_id) is not None
