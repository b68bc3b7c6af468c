"""`/surveys/{survey_id}/guardrails`: guardrail review.

Annotators correct the 0.5 m slice labels (most uncertain first, with a preview of the adjacency
correction), reviewers approve or reject the reconstructed guardrails and rebuild them from the
corrected slices. Writes carry the version the client saw: a mismatch answers 409 with the
records as they are now in `current`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from app.api.deps import Annotator, CurrentUser, Reviewer, SessionDep, wake_viewer
from app.api.errors import errors
from app.api.types import Id, Int64, Offset, Version
from app.core.errors import ConflictError, NotFoundError
from app.jobs.queue import enqueue
from app.review.guardrails import preview_correction, slice_position
from app.store.guardrail_review import (
    MAX_LABELS_PER_WRITE,
    GuardrailModelPublic,
    GuardrailSlicePublic,
    SliceLabelEdit,
    decide_model,
    get_model,
    list_models,
    list_slices,
    next_uncertain,
    put_slice_labels,
)
from app.store.guardrail_runs import latest_run
from app.store.models import ModelStatus
from app.store.surveys import get_survey

router = APIRouter(
    prefix="/surveys/{survey_id}/guardrails", tags=["guardrails"], responses=errors(401, 404)
)

Label = Annotated[int, Field(ge=0, le=1, description="0 other, 1 guardrail")]
MESH_TYPES = {"glb": "model/gltf-binary", "obj": "model/obj", "ply": "application/octet-stream"}


class SlicePage(BaseModel):
    total: int
    offset: int
    limit: int
    items: list[GuardrailSlicePublic]


class SliceLabelIn(BaseModel):
    id: Id
    version: Version = Field(ge=1, description="the slice's version the client saw")
    label: Label


class SliceLabelsIn(BaseModel):
    slices: list[SliceLabelIn] = Field(min_length=1, max_length=MAX_LABELS_PER_WRITE)


class NextUncertain(BaseModel):
    slice: GuardrailSlicePublic | None  # null: every slice has a human label
    position: list[float] | None = Field(
        None, description="world x, y, z to jump to: the slice's centre (float64)"
    )
    remaining: int  # slices no human labelled yet


class PreviewLabel(BaseModel):
    id: Id
    label: Label


class PreviewIn(BaseModel):
    labels: list[PreviewLabel] = Field(default_factory=list, max_length=MAX_LABELS_PER_WRITE)
    max_gap: Offset | None = Field(None, description="default: the run's")
    max_isolated: Offset | None = Field(None, description="default: the run's")


class PreviewSlice(BaseModel):
    id: int
    component_id: int
    slice_index: int
    label: int  # stored now
    proposed: int  # the input to the correction: given, else human, else the classifier's
    corrected_label: int


class PreviewOut(BaseModel):
    max_gap: int
    max_isolated: int
    guardrail_slices: int  # after the correction, whole survey
    changed: int  # slices whose corrected label differs from the stored one
    slices: list[PreviewSlice]  # those, plus the given ones


class DecisionIn(BaseModel):
    version: Version = Field(ge=1, description="the model's version the client saw")
    status: Literal["approved", "rejected"]


class RebuildIn(BaseModel):
    min_guardrail_length: float | None = Field(None, gt=0)
    join_gap: float | None = Field(None, ge=0)
    join_lateral: float | None = Field(None, ge=0)
    ground_clearance: float | None = Field(None, ge=0)


class JobRef(BaseModel):
    job_id: int
    kind: str
    status: str


@router.get("/slices", response_model=SlicePage, responses=errors(422))
def get_slices(
    survey_id: Id,
    _: CurrentUser,
    session: SessionDep,
    component: Int64 | None = None,
    label: Annotated[int | None, Query(ge=0, le=1)] = None,
    labelled: Annotated[bool | None, Query(description="only with / without a human label")] = None,
    uncertain_first: Annotated[
        bool, Query(description="probability nearest 0.5 first; else along the road")
    ] = False,
    offset: Offset = 0,
    limit: Annotated[int, Query(ge=1, le=5000)] = 100,
) -> SlicePage:
    """The survey's guardrail slices, one page."""
    total, rows = list_slices(
        session, survey_id, component=component, label=label, labelled=labelled,
        uncertain_first=uncertain_first, offset=offset, limit=limit,
    )  # fmt: skip
    items = [GuardrailSlicePublic.model_validate(r) for r in rows]
    return SlicePage(total=total, offset=offset, limit=limit, items=items)


@router.put("/slices", response_model=list[GuardrailSlicePublic], responses=errors(403, 409, 422))
def put_slices(
    survey_id: Id, body: SliceLabelsIn, user: Annotator, session: SessionDep, request: Request
) -> list[GuardrailSlicePublic]:
    """Label many slices at once (all or nothing); 409 with `current` on a stale version."""
    edits = [SliceLabelEdit(s.id, s.version, s.label) for s in body.slices]
    rows = put_slice_labels(session, survey_id, edits, user)
    wake_viewer(request)
    return [GuardrailSlicePublic.model_validate(r) for r in rows]


@router.get("/slices/next-uncertain", response_model=NextUncertain)
def get_next_uncertain(survey_id: Id, _: CurrentUser, session: SessionDep) -> NextUncertain:
    """The most uncertain slice no human labelled yet, with a world position to jump to."""
    row, remaining = next_uncertain(session, survey_id)
    if row is None:
        return NextUncertain(slice=None, position=None, remaining=0)
    position = slice_position(session, survey_id, row)
    return NextUncertain(
        slice=GuardrailSlicePublic.model_validate(row), position=position, remaining=remaining
    )


@router.post("/slices/preview-correction", response_model=PreviewOut, responses=errors(409, 422))
def post_preview_correction(
    survey_id: Id, body: PreviewIn, _: CurrentUser, session: SessionDep
) -> PreviewOut:
    """The adjacency correction applied to these labels, nothing saved (viewer preview)."""
    labels = {p.id: p.label for p in body.labels}
    result = preview_correction(session, survey_id, labels, body.max_gap, body.max_isolated)
    return PreviewOut.model_validate(result)


@router.get("/models", response_model=list[GuardrailModelPublic])
def get_models(
    survey_id: Id,
    _: CurrentUser,
    session: SessionDep,
    params: Annotated[bool, Query(description="include the full model parameters")] = False,
) -> list[GuardrailModelPublic]:
    """The reconstructed guardrails of the survey, along the road."""
    return [GuardrailModelPublic.of(m, params) for m in list_models(session, survey_id)]


@router.get(
    "/models/{model_id}/mesh",
    response_class=FileResponse,
    responses={**errors(422), 200: {"content": {t: {} for t in MESH_TYPES.values()}}},
)
def get_mesh(
    survey_id: Id,
    model_id: Id,
    _: CurrentUser,
    session: SessionDep,
    format: Literal["glb", "obj", "ply"] = "glb",
) -> FileResponse:
    """The model's assembled mesh (glb and ply relative to the model's origin, obj in world
    coordinates)."""
    get_survey(session, survey_id)
    model = get_model(session, survey_id, model_id)
    path = model.mesh_path if format == "glb" else (model.params.get("files") or {}).get(format)
    if not path:
        raise NotFoundError(f"guardrail model {model_id} has no {format} mesh")
    file = Path(path)
    if not file.is_file():
        raise NotFoundError(f"{file}: mesh of guardrail model {model_id} is missing")
    name = f"survey{survey_id}-guardrail-{model.guardrail_index:03d}-{model.kind.value}.{format}"
    return FileResponse(file, media_type=MESH_TYPES[format], filename=name)


@router.post(
    "/models/{model_id}/decision",
    response_model=GuardrailModelPublic,
    responses=errors(403, 409, 422),
)
def post_decision(
    survey_id: Id,
    model_id: Id,
    body: DecisionIn,
    user: Reviewer,
    session: SessionDep,
    request: Request,
) -> GuardrailModelPublic:
    """Approve or reject a reconstructed guardrail (reviewer); 409 with `current` when stale."""
    status = ModelStatus(body.status)
    row = decide_model(session, survey_id, model_id, body.version, status, user)
    wake_viewer(request)
    return GuardrailModelPublic.of(row)


@router.post("/rebuild", response_model=JobRef, status_code=202, responses=errors(403, 409, 422))
def post_rebuild(
    survey_id: Id, user: Reviewer, session: SessionDep, body: RebuildIn | None = None
) -> JobRef:
    """Queue `guardrail:rebuild`: the guardrails again from the corrected slice labels
    (reviewer). Decided models whose slices did not change keep their decision."""
    get_survey(session, survey_id)
    if latest_run(session, survey_id) is None:
        raise ConflictError(f"survey {survey_id} has no guardrail run yet; run run:guardrail")
    config = body.model_dump(exclude_none=True) if body is not None else {}
    job = enqueue(session, "guardrail:rebuild", config, survey_id, user.id)
    return JobRef(job_id=job.id, kind=job.kind, status=job.status.value)
