"""`/surveys/{survey_id}/clutter`: review the objects a clutter run removed.

A `run:clutter` job (POST /jobs) puts every instance it found up for review, pending. Anyone
logged in lists them (per frame, by decision or class) and fetches their mask images;
reviewers approve (remove the instance's points), reject (keep them) or reset them to pending
(the pipeline decides), many at once, each with the decision version they saw (a stale one: 409
with the current state); POST /recompute queues the job that rebuilds the cleaned and removed
maps from the decisions.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field
from sqlmodel import SQLModel

from app.api.deps import CurrentUser, Reviewer, SessionDep, SettingsDep, wake_viewer
from app.api.errors import errors
from app.api.schemas import JobPublic
from app.api.types import Id, Offset, Version
from app.core.errors import ConflictError, NotFoundError
from app.jobs.queue import enqueue
from app.store.clutter_review import (
    MAX_PAGE,
    RECOMPUTE_KIND,
    DecisionWrite,
    InstanceState,
    decide,
    frame_counts,
    get_instance,
    has_review,
    list_instances,
)
from app.store.models import Decision
from app.store.surveys import get_survey

router = APIRouter(
    prefix="/surveys/{survey_id}/clutter", tags=["clutter"], responses=errors(401, 404)
)

MAX_DECISIONS = 10_000


class InstancePublic(SQLModel):
    id: int
    frame_id: str
    instance_index: int = Field(description="the instance's number in its frame's membership")
    class_name: str = Field(description="person, car, ... or free-space (no camera mask)")
    point_count: int
    bbox: list[int] | None = Field(description="[u0, v0, u1, v1] pixels; null: not in the image")
    moving: bool | None
    track_id: int | None
    decision: Decision
    version: int = Field(description="send it back with a decision (optimistic concurrency)")
    user_id: int | None = Field(description="who approved or rejected it")
    decided_at: datetime | None
    mask_url: str | None = Field(description="the instance's mask image (PNG)")

    @classmethod
    def of(cls, s: InstanceState) -> InstancePublic:
        """The instance as listed; its mask's URL is the one field computed here."""
        url = f"/surveys/{s.survey_id}/clutter/instances/{s.id}/mask"
        return cls.model_validate(s, update={"mask_url": None if s.mask_path is None else url})


class InstancePage(BaseModel):
    total: int = Field(description="instances matching the filters")
    offset: int
    limit: int
    items: list[InstancePublic]


class FrameReview(BaseModel):
    frame_id: str
    instances: int
    pending: int


class DecisionIn(BaseModel):
    instance_id: Id
    version: Version = Field(ge=1, description="the decision version the reviewer saw")
    decision: Decision


class DecisionBatch(BaseModel):
    decisions: list[DecisionIn] = Field(min_length=1, max_length=MAX_DECISIONS)


@router.get("/instances", response_model=InstancePage, responses=errors(422))
def read_instances(
    survey_id: Id,
    _: CurrentUser,
    session: SessionDep,
    frame_id: Annotated[str | None, Query(max_length=64, description="one frame only")] = None,
    decision: Decision | None = None,
    class_name: Annotated[str | None, Query(max_length=32)] = None,
    offset: Offset = 0,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 100,
) -> InstancePage:
    """The survey's instances in frame order, one page at a time, with decision and version."""
    get_survey(session, survey_id)
    total, states = list_instances(
        session, survey_id, frame_id, decision, class_name, offset, limit
    )
    return InstancePage(
        total=total, offset=offset, limit=limit, items=[InstancePublic.of(s) for s in states]
    )


@router.get("/instances/{instance_id}", response_model=InstancePublic)
def read_instance(
    survey_id: Id, instance_id: Id, _: CurrentUser, session: SessionDep
) -> InstancePublic:
    """One instance (an id of another survey is not found here)."""
    get_survey(session, survey_id)
    return InstancePublic.of(get_instance(session, survey_id, instance_id))


@router.get(
    "/instances/{instance_id}/mask",
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}}, "description": "the mask image"}},
)
def read_mask(survey_id: Id, instance_id: Id, _: CurrentUser, session: SessionDep):
    """The instance's mask image: the camera image around it with its mask tinted and its
    points dotted (white: the pipeline removes them, black: keeps them), or a top view."""
    get_survey(session, survey_id)
    state = get_instance(session, survey_id, instance_id)
    if state.mask_path is None or not Path(state.mask_path).is_file():
        raise NotFoundError(f"clutter instance {instance_id} has no mask image")
    return FileResponse(state.mask_path, media_type="image/png")


@router.get("/frames", response_model=list[FrameReview])
def read_frames(survey_id: Id, _: CurrentUser, session: SessionDep) -> list[FrameReview]:
    """Every frame with its instance count and how many still wait for a decision."""
    get_survey(session, survey_id)
    return [FrameReview(**c.__dict__) for c in frame_counts(session, survey_id)]


@router.post("/decisions", response_model=list[InstancePublic], responses=errors(403, 409, 422))
def post_decisions(
    survey_id: Id, body: DecisionBatch, user: Reviewer, session: SessionDep, request: Request
) -> list[InstancePublic]:
    """Approve (remove the points), reject (keep them) or reset to pending, in one transaction.
    Any stale version rejects the whole batch with 409 and `current`: the decisions as they
    are now. Answers the instances after the write, in request order."""
    get_survey(session, survey_id)
    writes = [DecisionWrite(d.instance_id, d.version, d.decision) for d in body.decisions]
    states = decide(session, survey_id, writes, user.id)
    wake_viewer(request)
    return [InstancePublic.of(s) for s in states]


@router.post("/recompute", response_model=JobPublic, status_code=202, responses=errors(403, 409))
def post_recompute(
    survey_id: Id, user: Reviewer, session: SessionDep, settings: SettingsDep
) -> JobPublic:
    """Queue `clutter:recompute`: the cleaned and removed maps from the decisions (approved:
    removed, rejected: kept, pending: as the pipeline decided). 409 before any clutter run."""
    get_survey(session, survey_id)
    if not has_review(session, survey_id):
        raise ConflictError(f"survey {survey_id} has no clutter run to review; run clutter first")
    return JobPublic.model_validate(
        enqueue(session, RECOMPUTE_KIND, {}, survey_id, user.id, settings)
    )
