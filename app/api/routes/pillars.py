"""`/surveys/{survey_id}/pillars`: pillar labels for the labelling mode.

Reads are columnar (one array per field) because a 100 m x 100 m tile holds up to 250,000
pillars; writes are batches (one brush stroke or rectangle = one undoable action).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, BackgroundTasks, Query, Request, Response
from pydantic import BaseModel, Field, model_validator

from app.api.deps import Annotator, CurrentUser, SessionDep, wake_viewer
from app.api.errors import errors
from app.api.types import CellId, Coordinate, Id, Version
from app.core.labels import PillarClass
from app.store.models import LabelSource
from app.store.pillar_labels import NO_LABEL, STORE_GRID, LabelWrite, redo, undo, write_labels
from app.store.pillar_reads import label_counts, tile_json, uncertain_areas
from app.store.surveys import get_survey

router = APIRouter(
    prefix="/surveys/{survey_id}/pillars", tags=["pillars"], responses=errors(401, 404)
)

MAX_BATCH = 100_000
CLASS_NAMES = [c.name for c in PillarClass]


class PillarLabelIn(BaseModel):
    """One pillar by `cell_id`, or by a world position `x`, `y` inside it."""

    cell_id: CellId | None = None
    x: Coordinate | None = None
    y: Coordinate | None = None
    label: Annotated[int, Field(ge=0, le=3)] | None = Field(
        ..., description="0 ground, 1 high object, 2 short object, 3 phantom; null erases"
    )
    version: Version | None = Field(
        None,
        description="version the client saw (0: never labelled; an erased pillar is at its "
        "erase's version, as reads return it); mismatch -> 409",
    )

    @model_validator(mode="after")
    def _one_address(self) -> PillarLabelIn:
        if self.cell_id is None and (self.x is None or self.y is None):
            raise ValueError("give cell_id, or both x and y")
        return self


class LabelBatch(BaseModel):
    labels: list[PillarLabelIn] = Field(..., max_length=MAX_BATCH)


class LabelWriteOut(BaseModel):
    batch_id: int | None
    written: int
    cell_id: list[int]
    version: list[int]  # per pillar after the write (an erase's too: versions only grow)


class TileOut(BaseModel):
    """Columnar: entry i of every list is one (pillar, source) label."""

    cell_size: float
    origin: tuple[float, float]
    count: int
    cell_id: list[int]
    ix: list[int]  # grid index: centre x = origin[0] + (ix + 0.5) * cell_size
    iy: list[int]
    label: list[int]
    source: list[str]
    confidence: list[float | None]
    version: list[int]
    user_id: list[int | None]
    # erased human labels (no label, but a version a write over them must send), apart
    erased_cell_id: list[int]
    erased_version: list[int]


class UncertainAreaOut(BaseModel):
    x: float
    y: float
    pillars: int
    mean_confidence: float
    cell_ids: list[int]


class LabelStats(BaseModel):
    classes: list[str]
    human: list[int]
    model: list[int]


def _write_out(result: LabelWrite) -> LabelWriteOut:
    return LabelWriteOut(
        batch_id=result.batch_id,
        written=len(result.cell_ids),
        cell_id=result.cell_ids.tolist(),
        version=result.versions.tolist(),
    )


def _after_write(request: Request, background: BackgroundTasks) -> None:
    """Reviewed labels count towards the retraining trigger, checked after the answer is sent."""
    trigger = getattr(request.app.state, "retraining_trigger", None)
    if trigger is not None:
        background.add_task(trigger)


@router.put("/labels", response_model=LabelWriteOut, responses=errors(403, 409, 422))
def put_labels(
    survey_id: Id,
    batch: LabelBatch,
    user: Annotator,
    session: SessionDep,
    request: Request,
    background: BackgroundTasks,
) -> LabelWriteOut:
    """Write a batch of human labels in one transaction (one undoable action). Pillars may be
    addressed by cell id or by a world position; a stale `version` rejects the whole batch with
    409 and the current state of the stale pillars."""
    get_survey(session, survey_id)
    items = batch.labels
    cell_ids = np.array([-1 if i.cell_id is None else i.cell_id for i in items], dtype=np.int64)
    by_xy = np.array([i.cell_id is None for i in items], dtype=bool)
    if by_xy.any():
        xy = np.array([(i.x, i.y) for i, m in zip(items, by_xy, strict=True) if m])
        ix, iy = STORE_GRID.cell_index(xy).T
        cell_ids[by_xy] = STORE_GRID.cell_id(ix, iy)
    labels = np.array([NO_LABEL if i.label is None else i.label for i in items], dtype=np.int64)
    versions = [i.version for i in items]
    checked = versions if any(v is not None for v in versions) else None
    result = write_labels(session, survey_id, user.id, cell_ids, labels, checked)
    wake_viewer(request)
    _after_write(request, background)
    return _write_out(result)


@router.get(
    "/labels",
    response_class=Response,
    responses={200: {"model": TileOut, "description": "columnar labels"}, **errors(422)},
)
def get_labels(
    survey_id: Id,
    user: CurrentUser,
    session: SessionDep,
    x0: Annotated[Coordinate, Query(description="box in world coordinates (metres)")],
    y0: Coordinate,
    x1: Coordinate,
    y1: Coordinate,
    source: LabelSource | None = None,
) -> Response:
    """Labels of the pillars in a world box (at most 1 km x 1 km), human and model, columnar
    (entry i of every array is one label; `ix`, `iy` the pillar's grid index)."""
    get_survey(session, survey_id)
    body = tile_json(session, survey_id, (x0, y0, x1, y1), source)
    return Response(body, media_type="application/json")


@router.post("/undo", response_model=LabelWriteOut, responses=errors(403, 409))
def undo_labels(
    survey_id: Id, user: Annotator, session: SessionDep, request: Request
) -> LabelWriteOut:
    """Revert this user's newest labelling action on the survey (409 when there is none, or
    when someone changed those pillars since)."""
    get_survey(session, survey_id)
    result = undo(session, survey_id, user.id)
    wake_viewer(request)
    return _write_out(result)


@router.post("/redo", response_model=LabelWriteOut, responses=errors(403, 409))
def redo_labels(
    survey_id: Id, user: Annotator, session: SessionDep, request: Request
) -> LabelWriteOut:
    """Re-apply this user's most recently undone action (gone once they label anew)."""
    get_survey(session, survey_id)
    result = redo(session, survey_id, user.id)
    wake_viewer(request)
    return _write_out(result)


@router.get("/uncertain", response_model=list[UncertainAreaOut], responses=errors(422))
def uncertain(
    survey_id: Id,
    user: CurrentUser,
    session: SessionDep,
    threshold: Annotated[float, Query(gt=0, le=1)] = 0.9,
    area: Annotated[float, Query(gt=0, le=1000)] = 10.0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 20,
) -> list[UncertainAreaOut]:
    """The "uncertain first" queue: areas whose model pre-labels are least confident and not
    yet reviewed, most doubtful first; the viewer's "next uncertain area" jumps to the first."""
    get_survey(session, survey_id)
    areas = uncertain_areas(session, survey_id, threshold, area, limit)
    return [UncertainAreaOut(**a.__dict__) for a in areas]


@router.get("/stats", response_model=LabelStats)
def stats(survey_id: Id, user: CurrentUser, session: SessionDep) -> LabelStats:
    """Pillars per class, human labels and model pre-labels."""
    get_survey(session, survey_id)
    counts = label_counts(session, survey_id)
    return LabelStats(classes=CLASS_NAMES, human=counts["human"], model=counts["model"])
