"""`/surveys/{survey_id}/clutter`: review the objects a clutter run removed.

A `run:clutter` job (POST /jobs) puts every instance it found up for review, pending. Anyone
logged in lists them (per frame, by decision or class) and fetches their mask images;
reviewers approve (remove the instance's points), reject (keep them) or reset them to pending
(the pipeline decides), many at once, each with the decision version they saw (a stale one: 409
with the current state); POST /recompute queues the job that rebuilds the cleaned and removed
maps from the decisions.

Reviewers also correct an instance's extent: POST .../instances/{id}/remove-points takes the
listed points (indices in the frame) out of the instance, which keeps them (with the version
seen: the instance's version goes up, a stale one is 409); POST .../frames/{frame}/objects
makes a missed object of the listed points that belong to no instance, a new instance of a
clutter class, approved; POST .../frames/{frame}/objects/box does the same from a 2D box on the
frame's camera image (`app.review.box_objects`: the object the camera sees most in the box).
Recompute applies both (`app.store.clutter_corrections`).
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field
from sqlmodel import SQLModel

from app.api.deps import CurrentUser, Reviewer, SessionDep, SettingsDep, wake_viewer
from app.api.errors import errors
from app.api.schemas import JobPublic
from app.api.types import Id, Offset, Version
from app.core.errors import ConflictError, NotFoundError
from app.jobs.queue import enqueue
from app.review import clutter_corrections
from app.store.clutter_corrections import MAX_POINTS, OBJECT_CLASSES, Corrected
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


PointIndex = Annotated[int, Field(ge=0, le=2**31 - 1)]
ObjectClass = Literal.__getitem__(OBJECT_CLASSES)  # the clutter classes of app.core.labels
FrameId = Annotated[str, PathParam(min_length=1, max_length=64)]


class RemovePointsIn(BaseModel):
    version: int = Field(
        ge=1, le=2**63 - 1, description="the instance's decision version the reviewer saw"
    )
    points: list[PointIndex] = Field(
        min_length=1, max_length=MAX_POINTS, description="point indices in the instance's frame"
    )


class AddObjectIn(BaseModel):
    class_name: ObjectClass = Field(description="what the missed object is")  # type: ignore[valid-type]
    points: list[PointIndex] = Field(
        min_length=1,
        max_length=MAX_POINTS,
        description="point indices in the frame; those already in an instance are left to it",
    )


PixelCoordinate = Annotated[float, Field(ge=0, le=100_000, allow_inf_nan=False)]


class ImageBox(BaseModel):
    u0: PixelCoordinate = Field(description="left edge, pixels from the image's left")
    v0: PixelCoordinate = Field(description="top edge, pixels from the image's top")
    u1: PixelCoordinate = Field(description="right edge")
    v1: PixelCoordinate = Field(description="bottom edge")


class AddBoxObjectIn(BaseModel):
    class_name: ObjectClass = Field(description="what the missed object is")  # type: ignore[valid-type]
    box: ImageBox = Field(description="the object's box on the frame's camera image")


class CorrectionOut(BaseModel):
    instance: InstancePublic = Field(description="the instance after the correction")
    points: int = Field(description="how many points the correction moved")

    @classmethod
    def of(cls, done: Corrected) -> CorrectionOut:
        return cls(instance=InstancePublic.of(done.state), points=done.points)


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


@router.post(
    "/instances/{instance_id}/remove-points",
    response_model=CorrectionOut,
    responses=errors(403, 409, 422),
)
def post_remove_points(
    survey_id: Id,
    instance_id: Id,
    body: RemovePointsIn,
    user: Reviewer,
    session: SessionDep,
    request: Request,
) -> CorrectionOut:
    """Take the instance's points among `points` out of it: they are kept whatever its
    decision. 409 when `version` is not the instance's current one (with `current`) or a new
    run replaced the instances; 422 when no listed point belongs to the instance or one is
    outside the frame."""
    get_survey(session, survey_id)
    done = clutter_corrections.remove_points(
        session, survey_id, instance_id, body.version, body.points, user.id
    )
    wake_viewer(request)
    return CorrectionOut.of(done)


@router.post(
    "/frames/{frame_id}/objects",
    response_model=CorrectionOut,
    status_code=201,
    responses=errors(403, 409, 422),
)
def post_object(
    survey_id: Id,
    frame_id: FrameId,
    body: AddObjectIn,
    user: Reviewer,
    session: SessionDep,
    request: Request,
) -> CorrectionOut:
    """A missed object: the listed points that belong to no instance become a new instance of
    `class_name` on the frame, approved by you (its points are removed by the next recompute).
    404 for an unknown frame; 422 when every point already belongs to an instance."""
    get_survey(session, survey_id)
    done = clutter_corrections.add_object(
        session, survey_id, frame_id, body.class_name, body.points, user.id
    )
    wake_viewer(request)
    return CorrectionOut.of(done)


@router.post(
    "/frames/{frame_id}/objects/box",
    response_model=CorrectionOut,
    status_code=201,
    responses=errors(403, 409, 422),
)
def post_box_object(
    survey_id: Id,
    frame_id: FrameId,
    body: AddBoxObjectIn,
    user: Reviewer,
    session: SessionDep,
    request: Request,
) -> CorrectionOut:
    """A missed object outlined by a box on the frame's camera image (the clutter run's camera):
    the points of the object the camera sees most inside the box that belong to no instance
    become a new approved instance of `class_name`. 404 for an unknown frame; 409 when the frame
    has no camera image; 422 when the box covers no pixel or shows no free object."""
    get_survey(session, survey_id)
    b = body.box
    done = clutter_corrections.add_object_in_box(
        session, survey_id, frame_id, body.class_name,
        clutter_corrections.PixelBox.spanning((b.u0, b.v0), (b.u1, b.v1)), user.id,
    )  # fmt: skip
    wake_viewer(request)
    return CorrectionOut.of(done)


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
