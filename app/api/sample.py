"""First start: load the sample survey shipped in data_samples/ into an empty database."""

from __future__ import annotations

import logging
from pathlib import Path

from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.io import open_survey
from app.store.surveys import register_opened_survey, survey_count

log = logging.getLogger(__name__)

SAMPLE_FORMAT = "sim"


def load_sample_on_first_start(engine: Engine, sample: Path | None) -> int | None:
    """Register the sample survey when the database has no survey yet; returns its id."""
    if sample is None or not sample.is_dir():
        return None
    with Session(engine) as session:
        if survey_count(session):
            return None
        survey = open_survey(sample, SAMPLE_FORMAT)
        record = register_opened_survey(
            session,
            survey,
            format=SAMPLE_FORMAT,
            source_path=sample.resolve(),
            action="survey.sample",
        )
        log.info("loaded the sample survey %s (%d frames)", record.name, record.frame_count)
        return record.id
