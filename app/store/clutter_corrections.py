"""Reviewers' corrections of clutter instances: points taken out of an instance, missed objects
added (the anchor tools' "correct an object", beside approve / reject).

A run's membership (which instance owns each point of a frame, `<run>/instances/<frame>.npz`)
is never rewritten; a correction is a row of `clutter_correction` holding its points (int32
indices in the frame), applied over the membership in id order by whoever reads it
(`app.pipelines.clutter.review_corrections.corrected_membership`: the viewer, the API,
`clutter:recompute`, the SemanticKITTI export).

- `remove_points`: the points of an instance inside a reviewer's selection leave it and are
  kept. The instance changes, so its decision version goes up by one: a reviewer still holding
  the old version is refused (409) whether they decide or correct it, and so is this write
  when the version it was given is not the current one (`versions.check_versions`).
- `add_object`: the selected points that belong to no instance become a new instance of a
  clutter class (fresh id, the frame's next instance index, no mask image), approved by the
  reviewer at version 1. Points another correction gave to an instance meanwhile are left to
  it; none left is refused.

Both run in one write transaction (`write_transaction`: the membership they are checked
against cannot change before the commit), check that the membership the caller read belongs to
the survey's current run (a new run replaces the instances and, by cascade, their
corrections), audit (`clutter.remove_points`, `clutter.add_object`, the survey in the payload:
open viewers follow through the label feed) and commit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sqlalchemy as sa
from sqlmodel import Session

from app.core.errors import ConfigError, ConflictError, NotFoundError, StaleWriteError
from app.core.labels import CLUTTER_CLASS_SEMANTIC
from app.pipelines.clutter.review_corrections import (
    ADD,
    REMOVE,
    MembershipCorrection,
    corrected_membership,
)
from app.store import clutter_review
from app.store.clutter_review import InstanceState
from app.store.db import commit, write_transaction
from app.store.models import (
    AuditEvent,
    ClutterCorrection,
    ClutterDecision,
    ClutterInstance,
    Decision,
    Frame,
    utcnow,
)
from app.store.versions import check_versions, fresh_ids

REMOVE_ACTION = "clutter.remove_points"
ADD_ACTION = "clutter.add_object"
# what a reviewer may call an object they add: the run's camera classes (and moved-track)
OBJECT_CLASSES = tuple(CLUTTER_CLASS_SEMANTIC)
MAX_POINTS = 1_000_000  # points of one correction (an HDL-64E frame holds about 120,000)

_CORRECTION = ClutterCorrection.__table__
_INSTANCE = ClutterInstance.__table__
_DECISION = ClutterDecision.__table__
_AUDIT = AuditEvent.__table__
_FRAME = Frame.__table__


@dataclass(frozen=True)
class RunMembership:
    """One frame's membership as the run wrote it: the folder it was read from, per point the
    instance index (-1 none) and the pipeline's removed flag."""

    folder: Path
    frame_id: str
    owner: np.ndarray
    flags: np.ndarray


@dataclass(frozen=True)
class Corrected:
    """A correction's outcome: the instance after it, and how many points it moved."""

    state: InstanceState
    points: int


def current_run_folder(session: Session, survey_id: int) -> Path | None:
    """The folder of the clutter run whose instances the store holds (the mask images'), else
    the newest succeeded run's (one that found nothing); None before any run."""
    decisions = clutter_review.review_decisions(session, survey_id)
    folder = clutter_review.run_folder_of([d[3] for d in decisions])
    if folder is None:
        job = clutter_review.latest_run(session, survey_id)
        if job is not None and "instances" in (job.result or {}).get("files", {}):
            folder = Path(job.result["files"]["instances"]).parent
    return folder


def _corrections(rows: Sequence[sa.Row]) -> list[MembershipCorrection]:
    return [MembershipCorrection(r.kind, int(r.instance_index), _decode(r.points)) for r in rows]


def _query() -> sa.Select:
    return (
        sa.select(
            _CORRECTION.c.frame_id,
            _CORRECTION.c.kind,
            _CORRECTION.c.points,
            _INSTANCE.c.instance_index,
        )
        .select_from(_CORRECTION)
        .join(_INSTANCE, _INSTANCE.c.id == _CORRECTION.c.instance_id)
        .order_by(_CORRECTION.c.id)
    )


def frame_corrections(
    session: Session, survey_id: int, frame_id: str
) -> list[MembershipCorrection]:
    """The corrections of one frame, in the order they were written."""
    rows = session.connection().execute(
        _query().where(_CORRECTION.c.survey_id == survey_id, _CORRECTION.c.frame_id == frame_id)
    )
    return _corrections(rows.all())


def survey_corrections(session: Session, survey_id: int) -> dict[str, list[MembershipCorrection]]:
    """frame id -> its corrections in the order they were written, for every corrected frame."""
    out: dict[str, list[MembershipCorrection]] = {}
    rows = session.connection().execute(_query().where(_CORRECTION.c.survey_id == survey_id))
    for row in rows:
        out.setdefault(row.frame_id, []).extend(_corrections([row]))
    return out


def correction_counts(session: Session, survey_id: int) -> dict[str, int]:
    """How many corrections of each kind the survey's current instances have."""
    rows = session.connection().execute(
        sa.select(_CORRECTION.c.kind, sa.func.count())
        .where(_CORRECTION.c.survey_id == survey_id)
        .group_by(_CORRECTION.c.kind)
    )
    counts = {REMOVE: 0, ADD: 0}
    counts.update({kind: int(n) for kind, n in rows})
    return counts


def _encode(points: np.ndarray) -> bytes:
    return np.ascontiguousarray(points, dtype="<i4").tobytes()


def _decode(blob: bytes) -> np.ndarray:
    return np.frombuffer(blob, dtype="<i4").astype(np.int64)


def checked_points(points: Sequence[int] | np.ndarray, count: int, frame_id: str) -> np.ndarray:
    """The point indices as a sorted unique int64 array; one outside the frame's `count`
    points, none at all or more than MAX_POINTS -> ConfigError naming it."""
    values = np.asarray(points, dtype=np.int64).reshape(-1)
    if not 1 <= len(values) <= MAX_POINTS:
        raise ConfigError("points", f"give 1 to {MAX_POINTS:,} point indices, got {len(values)}")
    bad = np.flatnonzero((values < 0) | (values >= count))
    if len(bad):
        raise ConfigError(
            f"points[{int(bad[0])}]",
            f"point {int(values[bad[0]])} is not in frame {frame_id!r} ({count} points)",
        )
    return np.unique(values)


def check_frame(session: Session, survey_id: int, frame_id: str) -> None:
    """NotFoundError unless the survey has a frame `frame_id`."""
    known = session.connection().execute(
        sa.select(_FRAME.c.id).where(_FRAME.c.survey_id == survey_id, _FRAME.c.frame_id == frame_id)
    )
    if known.first() is None:
        raise NotFoundError(f"frame {frame_id!r} not found in survey {survey_id}")


def _check_run(session: Session, survey_id: int, membership: RunMembership) -> None:
    """The membership was read from the survey's current run (a new run may have replaced the
    instances since)."""
    folder = current_run_folder(session, survey_id)
    if folder is None or folder.resolve() != membership.folder.resolve():
        raise ConflictError(
            f"survey {survey_id}'s clutter instances were replaced by a new run meanwhile; reload"
        )


def remove_points(
    session: Session,
    survey_id: int,
    instance_id: int,
    version: int,
    points: Sequence[int] | np.ndarray,
    membership: RunMembership,
    user_id: int | None,
) -> Corrected:
    """Take the instance's points among `points` out of it (they are kept), given the decision
    version the reviewer saw; commits. Unknown instance -> NotFoundError; stale version ->
    StaleWriteError (nothing written); no point of the instance among them -> ConfigError."""
    with write_transaction(session):
        before = clutter_review.get_instance(session, survey_id, instance_id)
        check_versions(
            [instance_id], [version], [before.version], field="version",
            noun="clutter instance", states=lambda _: [before.current()],
        )  # fmt: skip
        if before.frame_id != membership.frame_id:
            raise ConflictError(f"the membership given is frame {membership.frame_id!r}'s")
        _check_run(session, survey_id, membership)
        owner, _ = corrected_membership(
            membership.owner,
            membership.flags,
            frame_corrections(session, survey_id, before.frame_id),
        )
        wanted = checked_points(points, len(owner), before.frame_id)
        mine = wanted[owner[wanted] == before.instance_index]
        if not len(mine):
            raise ConfigError(
                "points",
                f"none of the {len(wanted)} points belongs to clutter instance {instance_id} "
                f"(#{before.instance_index} of frame {before.frame_id!r})",
            )
        now = utcnow()
        conn = session.connection()
        bumped = conn.execute(
            sa.update(_DECISION)
            .where(_DECISION.c.instance_id == instance_id, _DECISION.c.version == before.version)
            .values(version=_DECISION.c.version + 1, updated_at=now)
        )
        if bumped.rowcount != 1:  # cannot happen under the write lock; never write unchecked
            raise StaleWriteError(
                f"clutter instance {instance_id} changed meanwhile; reload and retry",
                [clutter_review.get_instance(session, survey_id, instance_id).current()],
            )
        conn.execute(
            sa.update(_INSTANCE)
            .where(_INSTANCE.c.id == instance_id)
            .values(point_count=sa.func.max(_INSTANCE.c.point_count - len(mine), 0))
        )
        _insert(conn, survey_id, before.frame_id, instance_id, REMOVE, mine, user_id, now)
        after = clutter_review.get_instance(session, survey_id, instance_id)
        _audit(conn, REMOVE_ACTION, after, user_id, now, len(mine), before.point_count)
        commit(session)
    return Corrected(after, len(mine))


def add_object(
    session: Session,
    survey_id: int,
    frame_id: str,
    class_name: str,
    points: Sequence[int] | np.ndarray,
    membership: RunMembership,
    user_id: int | None,
    bbox: list[int] | None = None,
) -> Corrected:
    """A missed object: the points among `points` that belong to no instance become a new
    instance of `class_name` on the frame, approved by `user_id`; commits. Unknown frame ->
    NotFoundError; unknown class, or every point already in an instance -> ConfigError."""
    if class_name not in OBJECT_CLASSES:
        raise ConfigError("class_name", f"must be one of {', '.join(OBJECT_CLASSES)}")
    if membership.frame_id != frame_id:
        raise ConflictError(f"the membership given is frame {membership.frame_id!r}'s")
    with write_transaction(session):
        conn = session.connection()
        check_frame(session, survey_id, frame_id)
        _check_run(session, survey_id, membership)
        owner, _ = corrected_membership(
            membership.owner, membership.flags, frame_corrections(session, survey_id, frame_id)
        )
        wanted = checked_points(points, len(owner), frame_id)
        free = wanted[owner[wanted] < 0]
        if not len(free):
            raise ConfigError(
                "points", f"all {len(wanted)} points already belong to an instance of the frame"
            )
        stored_max = conn.execute(
            sa.select(sa.func.max(_INSTANCE.c.instance_index)).where(
                _INSTANCE.c.survey_id == survey_id, _INSTANCE.c.frame_id == frame_id
            )
        ).scalar()
        index = (
            max(int(membership.owner.max(initial=-1)), -1 if stored_max is None else stored_max) + 1
        )
        instance_id = fresh_ids(session, _INSTANCE, 1)
        now = utcnow()
        conn.execute(
            sa.insert(_INSTANCE),
            [
                {
                    "id": instance_id, "survey_id": survey_id, "frame_id": frame_id,
                    "instance_index": index, "class_name": class_name,
                    "point_count": len(free), "mask_path": None, "bbox": bbox, "moving": None,
                    "track_id": None, "created_at": now,
                }
            ],
        )  # fmt: skip
        conn.execute(
            sa.insert(_DECISION),
            [
                {
                    "instance_id": instance_id, "decision": Decision.approved, "version": 1,
                    "user_id": user_id, "decided_at": now, "created_at": now, "updated_at": now,
                }
            ],
        )  # fmt: skip
        _insert(conn, survey_id, frame_id, instance_id, ADD, free, user_id, now)
        after = clutter_review.get_instance(session, survey_id, instance_id)
        _audit(conn, ADD_ACTION, after, user_id, now, len(free), 0)
        commit(session)
    return Corrected(after, len(free))


def _insert(
    conn: sa.Connection,
    survey_id: int,
    frame_id: str,
    instance_id: int,
    kind: str,
    points: np.ndarray,
    user_id: int | None,
    now: object,
) -> None:
    conn.execute(
        sa.insert(_CORRECTION),
        [
            {
                "survey_id": survey_id, "frame_id": frame_id, "instance_id": instance_id,
                "kind": kind, "points": _encode(points), "point_count": len(points),
                "user_id": user_id, "created_at": now,
            }
        ],
    )  # fmt: skip


def _audit(
    conn: sa.Connection,
    action: str,
    after: InstanceState,
    user_id: int | None,
    now: object,
    moved: int,
    before_count: int,
) -> None:
    conn.execute(
        sa.insert(_AUDIT),
        [
            {
                "at": now,
                "user_id": user_id,
                "action": action,
                "entity": "clutter_instance",
                "entity_id": str(after.id),
                "payload": {
                    "survey_id": after.survey_id,
                    "frame_id": after.frame_id,
                    "instance_index": after.instance_index,
                    "class_name": after.class_name,
                    "points": moved,
                    "point_count_before": before_count,
                    "point_count_after": after.point_count,
                    "decision": after.decision.value,
                    "version": after.version,
                },
            }
        ],
    )
