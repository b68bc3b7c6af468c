"""Survey records: registering an opened survey (with its frames) and listing what is there."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from sqlmodel import Session, func, select

from app.store.db import commit
from app.store.models import Frame, Survey


@dataclass(frozen=True)
class FrameRecord:
    """What the store keeps of one frame (the points stay in the source files)."""

    frame_index: int
    frame_id: str
    timestamp: float | None
    point_count: int
    pose: list[float]  # 4x4 row-major


def survey_count(session: Session) -> int:
    return int(session.exec(select(func.count()).select_from(Survey)).one())


def register_survey(
    session: Session,
    *,
    name: str,
    format: str,
    source_path: str,
    frames: Sequence[FrameRecord],
    has_reference_labels: bool,
    poses_estimated: bool,
    origin: tuple[float, float, float],
    created_by: int | None = None,
) -> Survey:
    """Insert a survey and all its frames in one transaction."""
    survey = Survey(
        name=name,
        format=format,
        source_path=source_path,
        frame_count=len(frames),
        point_count=sum(f.point_count for f in frames),
        has_reference_labels=has_reference_labels,
        poses_estimated=poses_estimated,
        origin_x=origin[0],
        origin_y=origin[1],
        origin_z=origin[2],
        created_by=created_by,
    )
    session.add(survey)
    session.flush()
    session.add_all(
        Frame(
            survey_id=survey.id,
            frame_index=f.frame_index,
            frame_id=f.frame_id,
            timestamp=f.timestamp,
            point_count=f.point_count,
            pose=f.pose,
        )
        for f in frames
    )
    commit(session)
    session.refresh(survey)
    return survey
