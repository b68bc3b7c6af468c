"""Retraining the phantom CNN from human pillar labels in the store (the task run directly)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import text
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

from app.api.sample import load_sample_on_first_start
from app.core.errors import ConfigError
from app.core.settings import Settings
from app.io import open_survey
from app.jobs.registry import JobContext
from app.jobs.training_tasks import train_phantom
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.dataset import labelled_map_from_survey, labelled_pillars
from app.store.models import Job, ModelVersion, Survey
from app.store.pillar_labels import STORE_GRID
from tests.jobs.conftest import job_context


@pytest.fixture
def context(engine: Engine) -> JobContext:
    """A train:phantom job's context on a store holding the sample survey."""
    settings = Settings(data_dir=Path(engine.url.database).parent)
    survey_id = load_sample_on_first_start(engine, settings.sample_dir)
    with Session(engine) as session:
        session.add(Job(id=1, kind="train:phantom", survey_id=None))
        session.commit()
    return job_context(settings, engine, 1, survey_id)


def label_from_reference(context: JobContext, per_class: int) -> int:
    """Human labels = the simulator's pillar classes for a few pillars of each class."""
    with Session(context.engine) as session:
        survey = session.get(Survey, context.survey_id)
        source, fmt = survey.source_path, survey.format
    pm, labels = labelled_pillars(
        labelled_map_from_survey(open_survey(source, fmt)), PhantomConfig()
    )
    rng = np.random.default_rng(0)
    judged = np.zeros(len(labels), dtype=bool)
    judged[pm.candidates()] = True
    picks = []
    for cls in range(4):
        index = np.flatnonzero((labels == cls) & (judged | (cls == 0)))
        picks.append(rng.choice(index, size=min(per_class, len(index)), replace=False))
    pick = np.concatenate(picks)
    cells = STORE_GRID.cell_id(pm.pillars[pick, 0], pm.pillars[pick, 1])
    with context.engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO pillar_label (survey_id, cell_id, label, source, version, created_at,"
                " updated_at) VALUES (:s, :c, :l, 'human', 1, datetime('now'), datetime('now'))"
            ),
            [
                {"s": context.survey_id, "c": c, "l": int(v)}
                for c, v in zip(cells.tolist(), labels[pick].tolist(), strict=True)
            ],
        )
    return len(pick)


def test_retraining_registers_a_scored_version(context: JobContext) -> None:
    assert label_from_reference(context, 150) > 300
    result = train_phantom(context, {"epochs": 1, "rotations": 1, "per_class": 300})
    assert Path(result["files"]["checkpoint"]).is_file()
    with Session(context.engine) as session:
        versions = session.exec(select(ModelVersion).order_by(ModelVersion.id)).all()
    shipped, new = versions
    assert shipped.name == "shipped:phantom_cnn_context.pt"
    assert new.id == result["model_version_id"] and new.job_id == 1
    held_out = new.metrics["validation"]
    assert 0 <= held_out["macro"]["f1"] <= 100
    assert new.metrics["validation_labels"] > 0
    # promoted exactly when not worse than the version it was fine-tuned from
    not_worse = held_out["macro"]["f1"] >= new.metrics["baseline"]["macro"]["f1"]
    assert new.is_promoted == not_worse == result["promoted"]
    assert shipped.is_promoted != not_worse


def test_too_few_labels_is_one_clear_error(context: JobContext) -> None:
    with pytest.raises(ConfigError, match="labels: 0 human pillar labels"):
        train_phantom(context, {})
    with pytest.raises(ConfigError, match="config.holdout"):
        train_phantom(context, {"holdout": 2})
