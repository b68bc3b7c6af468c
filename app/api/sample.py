"""First start: load the sample survey shipped in data_samples/ into an empty database."""

from __future__ import annotations

import logging
from pathlib import Path

from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.io import Survey, open_survey
from app.store.surveys import FrameRecord, register_survey, survey_count

log = logging.getLogger(__name__)

SAMPLE_FORMAT = "sim"


def survey_frames(survey: Survey) -> list[FrameRecord]:
    return [
        FrameRecord(
            frame_index=f.index,
            frame_id=f.frame_id,
            timestamp=f.timestamp,
            point_count=int(f.point_count or 0),
            pose=[float(v) for v in f.pose.ravel()],
        )
        for f in survey.frames
    ]


def load_sample_on_first_start(engine: Engine, sample: Path | None) -> int | None:
    """Register the sample survey when the database has no survey yet; returns its id."""
    if sample is None or not sample.is_dir():
        return None
    with Session(engine) as session:
        if survey_count(session):
            return None
        survey = open_survey(sample, SAMPLE_FORMAT)
        first = survey.frames[0].pose[:3, 3] if len(survey) else (0.0, 0.0, 0.0)
        record = register_survey(
            session,
            name=survey.name,
            format=SAMPLE_FORMAT,
            source_path=str(sample.resolve()),
            frames=survey_frames(survey),
            has_reference_labels=bool(survey.reference_label_kinds),
            poses_estimated=survey.poses_estimated,
            origin=tuple(float(v) for v in first),
        )
        log.info("loaded the sample survey %s (%d frames)", record.name, record.frame_count)
        return record.id
