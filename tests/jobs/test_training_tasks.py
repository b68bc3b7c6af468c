"""Retraining the phantom CNN from human pillar labels in the store (the task run directly)."""

from __future__ import annotations

import os
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
from app.jobs.phantom_training_data import ClassCounts, training_blocker
from app.jobs.registry import JobContext, load_tasks
from app.jobs.training_tasks import PhantomRetrainConfig, retraining_priors, train_phantom
from app.jobs.worker import run_job
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.priors import class_priors
from app.pipelines.phantom.training.dataset import labelled_map_from_survey, labelled_pillars
from app.store.jobs import claim_next
from app.store.models import Job, JobStatus, ModelVersion, Survey
from app.store.pillar_labels import STORE_GRID, write_labels
from app.store.pillar_reads import reviewed_class_counts
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


def label_far_from_the_map(context: JobContext, n: int = 100_000) -> None:
    """N labels (ground / phantom) 2 km from the sample survey's points: pillars that hold no
    points, as one annotator's 100,000 labels in the issue."""
    ix, iy = np.mgrid[10_000:10_400, 0:250].reshape(2, -1)[:, :n]
    cells = STORE_GRID.cell_id(ix, iy)
    with Session(context.engine) as session:
        write_labels(session, context.survey_id, None, cells, 3 * (np.arange(n) % 2))


def test_labels_on_pillars_without_points_fail_with_one_clear_line(context: JobContext) -> None:
    """Was `ValueError: need at least one array to concatenate` from numpy."""
    label_far_from_the_map(context)
    with pytest.raises(ConfigError) as caught:
        train_phantom(context, {"epochs": 1, "rotations": 1})
    message = caught.value.message
    assert message == (
        "labels: no labelled pillar outside the map blocks held out for validation has points "
        "in its survey's map (labels outside the surveyed area?)"
    )


def test_a_failed_retraining_job_says_why_in_its_message(context: JobContext) -> None:
    """Through a worker: the job ends failed, its message the task's one line."""
    label_far_from_the_map(context, 2000)
    claimed = claim_next(context.engine, os.getpid())
    assert claimed is not None and claimed.kind == "train:phantom"
    status = run_job(context.engine, context.settings, claimed, load_tasks(), os.getppid())
    assert status == JobStatus.failed
    with Session(context.engine) as session:
        job = session.get(Job, claimed.id)
    assert job.message.startswith("labels: no labelled pillar outside the map blocks held out")
    assert "\n" not in job.message and "concatenate" not in job.message


def test_one_class_of_labels_is_refused_before_any_map_is_read(context: JobContext) -> None:
    cells = STORE_GRID.cell_id(np.arange(500), np.zeros(500, dtype=np.int64))
    with Session(context.engine) as session:
        write_labels(session, context.survey_id, None, cells, np.zeros(500, dtype=np.int64))
    with pytest.raises(ConfigError, match=r"labels: the training labels hold 1 class\(es\)"):
        train_phantom(context, {"epochs": 1, "rotations": 1})


def test_labels_in_one_block_cannot_hold_any_out(context: JobContext) -> None:
    cells = STORE_GRID.cell_id(np.arange(60), np.zeros(60, dtype=np.int64))  # 12 m, 2 blocks
    with Session(context.engine) as session:
        write_labels(session, context.survey_id, None, cells, np.arange(60) % 2)
    with pytest.raises(ConfigError, match="labels: the labels cover too few map blocks"):
        train_phantom(context, {"epochs": 1, "rotations": 1, "block_size": 50})


def test_a_due_retraining_refused_when_queued_is_logged_not_raised(
    engine: Engine, settings: Settings, monkeypatch: pytest.MonkeyPatch, caplog
) -> None:
    """The trigger runs after a label write's answer went out: a refusal when it queues (here
    the memory limit) is a warning in the log, never an exception in a background task."""
    from app.jobs import retraining

    due = retraining.RetrainingState(
        threshold=1, new_labels=5, pending_job_id=None, since_last_job=5
    )
    monkeypatch.setattr(retraining, "retraining_state", lambda session, settings: due)

    def over_the_limit(*args, **kwargs):
        raise ConfigError("config.epochs", "this run needs about 9,000 MB; the limit is 64 MB")

    monkeypatch.setattr(retraining, "enqueue", over_the_limit)
    trigger = retraining.RetrainingTrigger(engine, settings.model_copy(update={"retrain_every": 1}))
    with caplog.at_level("WARNING", logger="app.jobs.retraining"):
        assert trigger() is None
    assert "the limit is 64 MB" in caplog.text


def test_retrained_priors_are_the_labelled_survey_as_reviewed(context: JobContext) -> None:
    """Pre-labels on ten pillars (six ground, four phantom), two phantoms corrected to ground by
    a person, and a human label where the run judged nothing (not counted)."""
    rows = [(c, 0, "model") for c in range(1, 7)] + [(c, 3, "model") for c in range(7, 11)]
    rows += [(7, 0, "human"), (8, 0, "human"), (99, 1, "human")]
    with context.engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO pillar_label (survey_id, cell_id, label, source, confidence, version,"
                " created_at, updated_at) VALUES (:s, :c, :l, :src, 0.5, 1, datetime('now'),"
                " datetime('now'))"
            ),
            [{"s": context.survey_id, "c": c, "l": v, "src": src} for c, v, src in rows],
        )
    with Session(context.engine) as session:
        reviewed = reviewed_class_counts(session, context.survey_id)
    assert reviewed.tolist() == [8, 0, 0, 2]
    base = {"class_priors": [0.25] * 4, "class_priors_from": "simulated drives"}
    priors, origin = retraining_priors(reviewed, base, [context.survey_id])
    assert priors == class_priors(np.array([8, 0, 0, 2])).round(5).tolist()
    assert "10 pillars" in origin
    # no labelled survey had a phantom run: the base model's priors stay
    assert retraining_priors(np.zeros(4, np.int64), base, [1]) == ([0.25] * 4, "simulated drives")


def test_training_needs_two_classes_with_enough_pillars() -> None:
    cfg = PhantomRetrainConfig()
    held = np.array([10, 10, 0, 0])
    fine = ClassCounts(230, np.array([150, 60, 0, 10]), held, True)
    assert training_blocker(fine, cfg) is None
    short = ClassCounts(220, np.array([150, 40, 0, 10]), held, True)
    assert training_blocker(short, cfg) == (
        "retraining needs 2 classes with at least 50 labelled pillars outside the held-out "
        "blocks (ground 150, high_object 40, phantom 10)"
    )
