"""`/vocabulary`: the label vocabulary of `app.core.labels` as the dashboard shows it, so the
browser keeps no copy of its own (the pillar classes name the rows of metrics that do not name
them, e.g. a shipped model's validation)."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from app.api.deps import CurrentUser
from app.api.errors import errors
from app.core.labels import PILLAR_CLASS_NAMES

router = APIRouter(prefix="/vocabulary", tags=["vocabulary"], responses=errors(401))


class Vocabulary(BaseModel):
    pillar_classes: list[str] = Field(
        description="the phantom paper's pillar classes in label order (the label value is the "
        "index), as people read them"
    )


@router.get("", response_model=Vocabulary)
def vocabulary(_: CurrentUser) -> Vocabulary:
    """The label vocabulary: the pillar classes in label order."""
    return Vocabulary(pillar_classes=list(PILLAR_CLASS_NAMES))
