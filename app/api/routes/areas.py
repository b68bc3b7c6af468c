"""`/surveys/{survey_id}/areas`: the review workflow (work areas), and `export-readiness`.

Admins and reviewers cut a survey's drive into work areas (default 100 m each) and assign each
to an annotator (and, optionally, a reviewer); the assignee marks it labelled; a reviewer signs
it off or rejects it with a comment (back to open). The list shows each area's coverage: its
pillars with points, how many have a human label, model pre-labels nobody reviewed, clutter
decisions and guardrail slices / models still pending in its stretch. Writes carry the area's
version the client saw: a stale one is 409 with `current`; a step the area's state does not
allow is 409 naming the state. `GET /surveys/{id}/export-readiness` says what the exports
still wait for (they go on; the dashboard and `mmsclean export` show the warning).
"""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from app.api.deps import CurrentUser, Reviewer, SessionDep, SettingsDep
from app.api.errors import errors
from app.api.types import Id, Version
from app.review.work_areas import AreaCoverage, coverage, cut_areas
from app.store.models import utcnow
from app.store.surveys import get_survey
from app.store.work_areas import (
    DEFAULT_LENGTH_M,
    MAX_COMMENT,
    MAX_LENGTH_M,
    MIN_LENGTH_M,
    UNSET,
    Assignment,
    WorkAreaPublic,
    assign,
    export_readiness,
    list_areas,
    mark_labelled,
    reject,
    sign_off,
)

router = APIRouter(prefix="/surveys/{survey_id}", tags=["work areas"], responses=errors(401, 404))


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")  # a misspelt field is named, never ignored


class AreasCreate(Strict):
    length_m: float = Field(
        DEFAULT_LENGTH_M,
        ge=MIN_LENGTH_M,
        le=MAX_LENGTH_M,
        allow_inf_nan=False,
        description="metres of drive per area (the last one shorter)",
    )
    replace: bool = Field(False, description="cut again: the survey's areas go, sign-offs too")


class Versioned(Strict):
    version: Version = Field(ge=1, description="the area's version the client saw")


class AssignIn(Versioned):
    assignee_id: Id | None = Field(None, description="the annotator who labels it (null: nobody)")
    reviewer_id: Id | None = Field(
        None, description="the reviewer who signs it off (null: any reviewer)"
    )


class RejectIn(Versioned):
    comment: str = Field(min_length=1, max_length=MAX_COMMENT, description="what is wrong")


class CoveragePublic(BaseModel):
    pillars: int = Field(description="pillars with points in the area")
    human_labelled: int = Field(description="of them, with a human label")
    labelled_fraction: float = Field(description="human_labelled / pillars (0 without pillars)")
    model_unreviewed: int = Field(description="model pre-labels no human label confirmed")
    clutter_pending: int = Field(description="clutter instances in its frames still pending")
    slices_unreviewed: int = Field(description="guardrail slices no person labelled")
    models_pending: int = Field(description="guardrail models not reviewed")

    @classmethod
    def of(cls, c: AreaCoverage) -> CoveragePublic:
        return cls.model_validate(c, from_attributes=True)


class AreaWithCoverage(WorkAreaPublic):
    coverage: CoveragePublic


class ReadinessPublic(BaseModel):
    survey_id: int
    ready: bool = Field(description="nothing pending")
    pending_clutter_decisions: int
    areas: int = Field(description="work areas of the survey")
    areas_not_signed_off: list[int] = Field(description="their area indices")
    pending_guardrail_models: int
    unreviewed_guardrail_slices: int = Field(description="slices no person labelled (info)")
    pending: list[str] = Field(description="one phrase per thing pending")
    warning: str | None = Field(description="the line shown beside the exports; null: ready")
    checked_at: datetime


@router.get("/areas", response_model=list[AreaWithCoverage])
def read_areas(
    survey_id: Id, _: CurrentUser, session: SessionDep, settings: SettingsDep
) -> list[AreaWithCoverage]:
    """The survey's work areas along the drive, each with its state and coverage."""
    areas = list_areas(session, survey_id)
    counts = coverage(session, settings, survey_id, areas)
    return [
        AreaWithCoverage.model_validate(a, update={"coverage": CoveragePublic.of(c)})
        for a, c in zip(areas, counts, strict=True)
    ]


@router.post(
    "/areas",
    response_model=list[WorkAreaPublic],
    status_code=201,
    responses=errors(403, 409, 422),
)
def create_areas(
    survey_id: Id, body: AreasCreate, user: Reviewer, session: SessionDep, settings: SettingsDep
) -> list[WorkAreaPublic]:
    """Cut the survey's drive (its frame poses) into areas of `length_m` metres, each with the
    world box of its pillars. 409 when it has areas already, unless `replace`."""
    get_survey(session, survey_id)
    rows = cut_areas(session, settings, survey_id, body.length_m, user, replace=body.replace)
    return [WorkAreaPublic.model_validate(r) for r in rows]


@router.post(
    "/areas/{area_id}/assign", response_model=WorkAreaPublic, responses=errors(403, 409, 422)
)
def post_assign(
    survey_id: Id, area_id: Id, body: AssignIn, user: Reviewer, session: SessionDep
) -> WorkAreaPublic:
    """Set the assignee and / or the reviewer (admins and reviewers); a field left out stays."""
    sent = body.model_fields_set
    assignment = Assignment(
        assignee_id=body.assignee_id if "assignee_id" in sent else UNSET,
        reviewer_id=body.reviewer_id if "reviewer_id" in sent else UNSET,
    )
    return WorkAreaPublic.model_validate(
        assign(session, survey_id, area_id, body.version, assignment, user)
    )


@router.post(
    "/areas/{area_id}/labelled", response_model=WorkAreaPublic, responses=errors(403, 409, 422)
)
def post_labelled(
    survey_id: Id, area_id: Id, body: Versioned, user: CurrentUser, session: SessionDep
) -> WorkAreaPublic:
    """The assignee says the area is labelled (open -> labelled)."""
    return WorkAreaPublic.model_validate(
        mark_labelled(session, survey_id, area_id, body.version, user)
    )


@router.post(
    "/areas/{area_id}/sign-off", response_model=WorkAreaPublic, responses=errors(403, 409, 422)
)
def post_sign_off(
    survey_id: Id, area_id: Id, body: Versioned, user: Reviewer, session: SessionDep
) -> WorkAreaPublic:
    """A reviewer accepts the area (labelled -> signed_off): the area's reviewer when it has
    one, or an admin."""
    return WorkAreaPublic.model_validate(sign_off(session, survey_id, area_id, body.version, user))


@router.post(
    "/areas/{area_id}/reject", response_model=WorkAreaPublic, responses=errors(403, 409, 422)
)
def post_reject(
    survey_id: Id, area_id: Id, body: RejectIn, user: Reviewer, session: SessionDep
) -> WorkAreaPublic:
    """A reviewer sends the area back to its annotator with a comment (labelled or signed_off
    -> open)."""
    return WorkAreaPublic.model_validate(
        reject(session, survey_id, area_id, body.version, body.comment, user)
    )


@router.get("/export-readiness", response_model=ReadinessPublic)
def read_export_readiness(survey_id: Id, _: CurrentUser, session: SessionDep) -> ReadinessPublic:
    """What the exports still wait for: pending clutter decisions, work areas not signed off,
    guardrail models not reviewed. Exports are not refused; `warning` is the line to show."""
    r = export_readiness(session, survey_id)
    return ReadinessPublic(
        survey_id=r.survey_id,
        ready=r.ready,
        pending_clutter_decisions=r.pending_clutter_decisions,
        areas=r.areas,
        areas_not_signed_off=r.areas_not_signed_off,
        pending_guardrail_models=r.pending_guardrail_models,
        unreviewed_guardrail_slices=r.unreviewed_guardrail_slices,
        pending=r.pending,
        warning=r.warning,
        checked_at=utcnow(),
    )
