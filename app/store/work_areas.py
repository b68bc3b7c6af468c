"""Work areas: a survey cut into stretches of its drive that annotators label and reviewers sign
off (the jobs of CVAT, the samples of Segments.ai), and what an export still waits for.

An area is `open` while its annotator labels it, `labelled` once the annotator (its assignee)
says it is done, `signed_off` once a reviewer accepts it; a reviewer who rejects it (with a
comment) sends it back to `open`, from `labelled` or from `signed_off`. Admins and reviewers cut
and assign areas. Every write carries the version the client saw (`app.store.versions`: a
stale one is 409 with the area as it is now), is checked and written in one transaction
(`write_transaction`) and audited as `work_area.<action>`. Areas cut again replace a survey's
areas whole, under ids no area ever had (`fresh_ids`).

Where the areas lie (stations, boxes) and which pillars each holds are worked out from the
survey's map in `app.review.work_areas`; this module holds the rows and the counts the coverage
and the export readiness are made of, read as arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
from sqlalchemy import text
from sqlmodel import Session, col, func, select

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
    AreaState,
    ClutterDecision,
    ClutterInstance,
    Decision,
    Frame,
    GuardrailModel,
    GuardrailSlice,
    ModelStatus,
    Role,
    User,
    WorkArea,
    WorkAreaBase,
    utcnow,
)
from app.store.surveys import get_survey
from app.store.users import get_user, has_role
from app.store.versions import check_versions, fresh_ids

DEFAULT_LENGTH_M = 100.0  # metres of drive per area
MIN_LENGTH_M = 5.0
MAX_LENGTH_M = 10_000.0
MAX_AREAS = 10_000  # per survey: a 1,000 km drive at 100 m
MAX_COMMENT = 1000

_AREA = WorkArea.__table__


class WorkAreaPublic(WorkAreaBase):
    """A work area as the API shows it (its row's columns)."""

    id: int
    version: int
    created_at: datetime
    updated_at: datetime


@dataclass(frozen=True)
class AreaPlan:
    """Where one new area lies: its stretch of the drive and the world box of its pillars."""

    station_start: float
    station_end: float
    box: tuple[float, float, float, float]  # x_min, y_min, x_max, y_max (world, float64)


# --- reads --------------------------------------------------------------------------------


def list_areas(session: Session, survey_id: int) -> list[WorkArea]:
    """The survey's areas along the drive."""
    get_survey(session, survey_id)
    query = select(WorkArea).where(WorkArea.survey_id == survey_id).order_by(WorkArea.area_index)
    return list(session.exec(query).all())


def get_area(session: Session, survey_id: int, area_id: int) -> WorkArea:
    row = session.get(WorkArea, area_id)
    if row is None or row.survey_id != survey_id:
        raise NotFoundError(f"work area {area_id} not found in survey {survey_id}")
    return row


def _current(row: WorkArea) -> dict[str, Any]:
    return WorkAreaPublic.model_validate(row).model_dump(mode="json")


# --- cutting ------------------------------------------------------------------------------


def check_length(length_m: float) -> float:
    """The area length, bounded (`length_m` names the field in the error)."""
    if not np.isfinite(length_m) or not MIN_LENGTH_M <= length_m <= MAX_LENGTH_M:
        raise ConfigError(
            "length_m", f"must be {MIN_LENGTH_M:g} to {MAX_LENGTH_M:g} metres, not {length_m}"
        )
    return float(length_m)


def replace_areas(
    session: Session,
    survey_id: int,
    plans: Sequence[AreaPlan],
    user: User,
    *,
    length_m: float,
    replace: bool = False,
) -> list[WorkArea]:
    """Store the survey's areas, in drive order. A survey that has areas keeps them (409)
    unless `replace`: then they all go, assignments and sign-offs with them (audited)."""
    get_survey(session, survey_id)
    if not has_role(user, Role.reviewer):
        raise PermissionDeniedError(
            f"user {user.username!r} is {user.role.value}; cutting work areas needs a reviewer"
        )
    if not plans:
        raise ConfigError("length_m", "the survey's drive gives no area")
    if len(plans) > MAX_AREAS:
        raise ConfigError(
            "length_m", f"{len(plans)} areas; at most {MAX_AREAS} per survey, choose a longer one"
        )
    with write_transaction(session):
        existing = session.exec(
            select(WorkArea.id, WorkArea.state).where(WorkArea.survey_id == survey_id)
        ).all()
        if existing and not replace:
            raise ConflictError(
                f"survey {survey_id} already has {len(existing)} work areas; "
                "send replace: true to cut them again (their assignments and sign-offs go)"
            )
        first = fresh_ids(session, _AREA, len(plans))
        if existing:
            session.connection().execute(_AREA.delete().where(_AREA.c.survey_id == survey_id))
        now = utcnow()
        rows = [
            WorkArea(
                id=first + k,
                created_at=now,
                updated_at=now,
                survey_id=survey_id,
                area_index=k,
                station_start=float(p.station_start),
                station_end=float(p.station_end),
                x_min=float(p.box[0]),
                y_min=float(p.box[1]),
                x_max=float(p.box[2]),
                y_max=float(p.box[3]),
            )
            for k, p in enumerate(plans)
        ]
        session.add_all(rows)
        signed = sum(1 for _, state in existing if state == AreaState.signed_off)
        audit(
            session, user.id, "work_area.cut", "survey", survey_id, length_m=float(length_m),
            areas=len(rows), replaced=len(existing), replaced_signed_off=signed,
        )  # fmt: skip
        commit(session)
    return list_areas(session, survey_id)


# --- the workflow -------------------------------------------------------------------------

_UNSET = object()


@dataclass(frozen=True)
class Assignment:
    """Who labels and who reviews an area; a field left out stays as it is (None: nobody)."""

    assignee_id: int | None | object = _UNSET
    reviewer_id: int | None | object = _UNSET

    def changes(self) -> dict[str, int | None]:
        return {
            k: v  # type: ignore[misc]
            for k, v in (("assignee_id", self.assignee_id), ("reviewer_id", self.reviewer_id))
            if v is not _UNSET
        }


UNSET = _UNSET  # for callers building an Assignment field by field


def _in_transaction(
    session: Session, survey_id: int, area_id: int, version: int
) -> tuple[WorkArea, dict[str, Any]]:
    """The area as it is now, inside the write's transaction, checked against `version`."""
    row = get_area(session, survey_id, area_id)
    session.refresh(row)
    check_versions(
        [area_id], [version], [row.version], field="version", noun="work area",
        states=lambda _: _current(row),
    )  # fmt: skip
    return row, _current(row)


def _finish(session: Session, survey_id: int, row: WorkArea) -> WorkArea:
    try:
        commit(session)
    except ConflictError as exc:  # lost a race after the check: report what won
        now = get_area(session, survey_id, int(row.id))
        session.refresh(now)
        raise StaleWriteError(str(exc), _current(now)) from exc
    session.refresh(row)
    return row


def _check_user(session: Session, user_id: int, what: str, role: Role) -> User:
    try:
        person = get_user(session, user_id)
    except NotFoundError as exc:
        raise ConfigError(what, f"no user {user_id}") from exc
    if not person.is_active:
        raise ConfigError(what, f"user {person.username!r} is deactivated")
    if not has_role(person, role):
        raise ConfigError(
            what, f"user {person.username!r} is {person.role.value}; a {what} must be {role.value}"
        )
    return person


def assign(
    session: Session,
    survey_id: int,
    area_id: int,
    version: int,
    assignment: Assignment,
    user: User,
) -> WorkArea:
    """An admin or reviewer sets the area's assignee (an annotator or above) and / or its
    reviewer (a reviewer or above). A signed-off area is reassigned only after a rejection."""
    get_survey(session, survey_id)
    if not has_role(user, Role.reviewer):
        raise PermissionDeniedError(
            f"user {user.username!r} is {user.role.value}; assigning work areas needs a reviewer"
        )
    get_area(session, survey_id, area_id)  # an unknown area is 404 before any field
    changes = assignment.changes()
    if not changes:
        raise ConfigError("assignee_id", "give assignee_id and / or reviewer_id (null: nobody)")
    for key, role in (("assignee_id", Role.annotator), ("reviewer_id", Role.reviewer)):
        if changes.get(key) is not None:
            _check_user(session, int(changes[key]), key.removesuffix("_id"), role)
    with write_transaction(session):
        row, before = _in_transaction(session, survey_id, area_id, version)
        if row.state == AreaState.signed_off:
            raise ConflictError(
                f"work area {row.area_index} is signed off; reject it (reopen) before reassigning"
            )
        for key, value in changes.items():
            setattr(row, key, value)
        session.add(row)
        audit(
            session, user.id, "work_area.assign", "work_area", row.id, survey_id=survey_id,
            before={k: before[k] for k in changes}, after=changes,
        )  # fmt: skip
        return _finish(session, survey_id, row)


def _transition(
    session: Session,
    survey_id: int,
    area_id: int,
    version: int,
    user: User,
    *,
    action: str,
    allowed_from: tuple[AreaState, ...],
    to: AreaState,
    who: Any,
    comment: str | None = None,
) -> WorkArea:
    with write_transaction(session):
        row, before = _in_transaction(session, survey_id, area_id, version)
        who(row)
        if row.state not in allowed_from:
            ways = " or ".join(s.value for s in allowed_from)
            raise ConflictError(
                f"work area {row.area_index} is {row.state.value}; {action.replace('_', ' ')}"
                f" needs it {ways}"
            )
        row.state = to
        if to == AreaState.open or to == AreaState.signed_off:
            row.decided_by, row.decided_at = user.id, utcnow()
        if comment is not None:
            row.comment = comment
        session.add(row)
        details = {} if comment is None else {"comment": comment}
        audit(
            session, user.id, f"work_area.{action}", "work_area", row.id, survey_id=survey_id,
            before=before["state"], after=to.value, **details,
        )  # fmt: skip
        return _finish(session, survey_id, row)


def mark_labelled(
    session: Session, survey_id: int, area_id: int, version: int, user: User
) -> WorkArea:
    """The area's assignee says its labelling is done: open -> labelled."""
    get_survey(session, survey_id)

    def only_the_assignee(row: WorkArea) -> None:
        if row.assignee_id is None:
            raise ConflictError(f"work area {row.area_index} has no assignee; assign it first")
        if row.assignee_id != user.id:
            raise PermissionDeniedError(
                f"only the assignee (user {row.assignee_id}) may mark work area "
                f"{row.area_index} labelled"
            )

    return _transition(
        session, survey_id, area_id, version, user, action="mark_labelled",
        allowed_from=(AreaState.open,), to=AreaState.labelled, who=only_the_assignee,
    )  # fmt: skip


def _a_reviewer_of(user: User, verb: str):
    if not has_role(user, Role.reviewer):
        raise PermissionDeniedError(
            f"user {user.username!r} is {user.role.value}; to {verb} a work area needs a reviewer"
        )

    def check(row: WorkArea) -> None:
        if row.reviewer_id is not None and row.reviewer_id != user.id and user.role != Role.admin:
            raise PermissionDeniedError(
                f"work area {row.area_index} is reviewed by user {row.reviewer_id}; "
                f"only they or an admin may {verb} it"
            )

    return check


def sign_off(session: Session, survey_id: int, area_id: int, version: int, user: User) -> WorkArea:
    """A reviewer (the area's, when it has one; or an admin) accepts it: labelled -> signed_off."""
    get_survey(session, survey_id)
    who = _a_reviewer_of(user, "sign off")
    return _transition(
        session, survey_id, area_id, version, user, action="sign_off",
        allowed_from=(AreaState.labelled,), to=AreaState.signed_off, who=who, comment="",
    )  # fmt: skip


def reject(
    session: Session, survey_id: int, area_id: int, version: int, comment: str, user: User
) -> WorkArea:
    """A reviewer sends the area back to its annotator with a comment: labelled or signed_off
    -> open."""
    get_survey(session, survey_id)
    who = _a_reviewer_of(user, "reject")
    comment = (comment or "").strip()
    if not comment:
        raise ConfigError("comment", "say what is wrong: a rejection needs a comment")
    if len(comment) > MAX_COMMENT:
        raise ConfigError("comment", f"at most {MAX_COMMENT} characters")
    return _transition(
        session, survey_id, area_id, version, user, action="reject",
        allowed_from=(AreaState.labelled, AreaState.signed_off), to=AreaState.open, who=who,
        comment=comment,
    )  # fmt: skip


# --- what the coverage counts, as arrays --------------------------------------------------


def _cells(session: Session, sql: str, survey_id: int) -> np.ndarray:
    rows = session.connection().execute(text(sql), {"s": survey_id}).all()
    return np.asarray(rows, dtype=np.int64).reshape(-1)


def human_cells(session: Session, survey_id: int) -> np.ndarray:
    """Sorted cell ids of the survey's pillars with a human label."""
    return _cells(
        session,
        "SELECT cell_id FROM pillar_label WHERE survey_id = :s AND source = 'human' "
        "ORDER BY cell_id",
        survey_id,
    )


def unreviewed_model_cells(session: Session, survey_id: int) -> np.ndarray:
    """Sorted cell ids of model pre-labels no human label has confirmed or replaced."""
    return _cells(
        session,
        "SELECT m.cell_id FROM pillar_label AS m WHERE m.survey_id = :s AND m.source = 'model' "
        "AND NOT EXISTS (SELECT 1 FROM pillar_label AS h WHERE h.survey_id = m.survey_id "
        "AND h.cell_id = m.cell_id AND h.source = 'human') ORDER BY m.cell_id",
        survey_id,
    )


def frame_stations(session: Session, survey_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(frame_index, station) of every frame: metres along the frame poses, in frame order."""
    rows = session.exec(
        select(Frame.frame_index, Frame.pose)
        .where(Frame.survey_id == survey_id)
        .order_by(Frame.frame_index)
    ).all()
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0)
    index = np.asarray([r[0] for r in rows], dtype=np.int64)
    xyz = np.asarray([r[1] for r in rows], dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    return index, arc_length(xyz)


def pending_clutter_by_frame(session: Session, survey_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(frame_index, pending decisions) of the frames with clutter instances still pending."""
    rows = session.exec(
        select(Frame.frame_index, func.count())
        .select_from(ClutterInstance)
        .join(ClutterDecision, col(ClutterDecision.instance_id) == col(ClutterInstance.id))
        .join(
            Frame,
            (col(Frame.survey_id) == col(ClutterInstance.survey_id))
            & (col(Frame.frame_id) == col(ClutterInstance.frame_id)),
        )
        .where(ClutterInstance.survey_id == survey_id, ClutterDecision.decision == Decision.pending)
        .group_by(Frame.frame_index)
    ).all()
    a = np.asarray(rows, dtype=np.int64).reshape(-1, 2)
    return a[:, 0], a[:, 1]


def unreviewed_slice_stations(session: Session, survey_id: int) -> np.ndarray:
    """Stations of the guardrail slices no person labelled yet."""
    rows = session.exec(
        select(GuardrailSlice.station_m).where(
            GuardrailSlice.survey_id == survey_id, col(GuardrailSlice.labelled_by).is_(None)
        )
    ).all()
    return np.asarray(rows, dtype=np.float64).reshape(-1)


def pending_model_stations(session: Session, survey_id: int) -> np.ndarray:
    """The middle station of each guardrail model still pending (NaN: its run stored none)."""
    rows = session.exec(
        select(GuardrailModel.params).where(
            GuardrailModel.survey_id == survey_id, GuardrailModel.status == ModelStatus.pending
        )
    ).all()
    spans = [(p or {}).get("station_m") or (np.nan, np.nan) for p in rows]
    return np.asarray(spans, dtype=np.float64).reshape(-1, 2).mean(axis=1)


# --- export readiness ---------------------------------------------------------------------


@dataclass(frozen=True)
class Readiness:
    """What the survey's review still waits for; exports go on, with a warning."""

    survey_id: int
    pending_clutter_decisions: int
    areas: int
    areas_not_signed_off: list[int] = field(default_factory=list)  # area indices
    pending_guardrail_models: int = 0
    unreviewed_guardrail_slices: int = 0  # slices no person labelled (not in the warning)

    @property
    def ready(self) -> bool:
        return not (
            self.pending_clutter_decisions
            or self.areas_not_signed_off
            or self.pending_guardrail_models
        )

    @property
    def pending(self) -> list[str]:
        """One phrase per thing pending, for the warning line."""
        parts = []
        n = self.pending_clutter_decisions
        if n:
            parts.append(f"{n} clutter decision{'s' if n != 1 else ''} pending")
        waiting = self.areas_not_signed_off
        if waiting:
            shown = ", ".join(str(i) for i in waiting[:10]) + (", ..." if len(waiting) > 10 else "")
            parts.append(f"{len(waiting)} of {self.areas} work areas not signed off ({shown})")
        n = self.pending_guardrail_models
        if n:
            parts.append(f"{n} guardrail model{'s' if n != 1 else ''} not reviewed")
        return parts

    @property
    def warning(self) -> str | None:
        """The one line the dashboard and `mmsclean export` show; None when nothing waits."""
        if self.ready:
            return None
        return f"review not finished: {'; '.join(self.pending)}. Exports show the current state."


def export_readiness(session: Session, survey_id: int) -> Readiness:
    """Pending clutter decisions, work areas not signed off, guardrail models not reviewed."""
    get_survey(session, survey_id)
    clutter = session.exec(
        select(func.count())
        .select_from(ClutterDecision)
        .join(ClutterInstance, col(ClutterInstance.id) == col(ClutterDecision.instance_id))
        .where(ClutterInstance.survey_id == survey_id, ClutterDecision.decision == Decision.pending)
    ).one()
    areas = session.exec(
        select(WorkArea.area_index, WorkArea.state)
        .where(WorkArea.survey_id == survey_id)
        .order_by(WorkArea.area_index)
    ).all()
    models = session.exec(
        select(func.count()).where(
            GuardrailModel.survey_id == survey_id, GuardrailModel.status == ModelStatus.pending
        )
    ).one()
    slices = session.exec(
        select(func.count()).where(
            GuardrailSlice.survey_id == survey_id, col(GuardrailSlice.labelled_by).is_(None)
        )
    ).one()
    return Readiness(
        survey_id=survey_id,
        pending_clutter_decisions=int(clutter),
        areas=len(areas),
        areas_not_signed_off=[int(i) for i, s in areas if s != AreaState.signed_off],
        pending_guardrail_models=int(models),
        unreviewed_guardrail_slices=int(slices),
    )
