"""run:phantom's parts around the pipeline: pre-label rows on the store grid, replacing a
survey's model labels, the model version row, progress mapping (the full run is exercised
through the API in tests/api/test_jobs.py)."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import text
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

from app.core.errors import ConfigError
from app.core.settings import Settings
from app.jobs.cluster import TILES_PROGRESS, tile_progress
from app.jobs.phantom_tasks import (
    INGEST_AT,
    model_label_rows,
    model_version_for,
    parse_config,
    run_phantom,
)
from app.pipelines.phantom.model import DEFAULT_MODEL, PAPER_MODEL
from app.store.model_labels import store_model_labels
from app.store.model_versions import ensure_shipped_version
from app.store.models import AuditEvent, PillarLabel, Pipeline, Survey, utcnow
from app.store.pillar_labels import STORE_GRID
from tests.jobs.conftest import job_context


@pytest.fixture
def survey_id(engine: Engine) -> int:
    with Session(engine) as session:
        survey = Survey(
            name="street", format="sim", source_path="/nowhere", sensor_kind="profile",
            sensor_note="simulator: profile scanner",
        )  # fmt: skip
        session.add(survey)
        session.commit()
        return survey.id


def pillars_npz(path: Path, pillars: np.ndarray, probs: np.ndarray, classified, cell_size=0.2):
    np.savez(
        path,
        pillars=np.asarray(pillars, dtype=np.int64),
        probabilities=np.asarray(probs, dtype=np.float32),
        classified=np.asarray(classified, dtype=bool),
        cell_size=cell_size,
    )
    return path


def test_rows_are_the_judged_pillars_on_the_store_grid(tmp_path: Path) -> None:
    pillars = np.array([[-3, 7], [10, -2], [500_000, 12], [4, 4]])  # 100 km east: still exact
    probs = np.array(
        [[0.1, 0.7, 0.1, 0.1], [1, 0, 0, 0], [0.05, 0.05, 0.1, 0.8], [0.2, 0.2, 0.5, 0.1]]
    )
    cells, labels, confidence = model_label_rows(
        pillars_npz(tmp_path / "p.npz", pillars, probs, [True, False, True, True])
    )
    judged = pillars[[0, 2, 3]]
    expected = STORE_GRID.cell_id(judged[:, 0], judged[:, 1])
    order = np.argsort(expected)
    np.testing.assert_array_equal(cells, expected[order])
    np.testing.assert_array_equal(labels, np.array([1, 3, 2])[order])
    np.testing.assert_allclose(confidence, np.array([0.7, 0.8, 0.5])[order], rtol=1e-6)


def test_a_finer_run_grid_keeps_the_most_confident_pillar_per_cell(tmp_path: Path) -> None:
    pillars = np.array([[0, 0], [1, 1], [2, 0]])  # 0.1 m pillars: the first two share a cell
    probs = np.array([[0.6, 0.4, 0, 0], [0, 0.1, 0, 0.9], [0, 0, 1.0, 0]])
    cells, labels, confidence = model_label_rows(
        pillars_npz(tmp_path / "p.npz", pillars, probs, [True] * 3, cell_size=0.1)
    )
    np.testing.assert_array_equal(cells, STORE_GRID.cell_id([0, 1], [0, 0]))
    np.testing.assert_array_equal(labels, [3, 2])
    np.testing.assert_allclose(confidence, [0.9, 1.0], rtol=1e-6)


def model_rows(engine: Engine, survey_id: int, source: str = "model") -> list[tuple]:
    with engine.connect() as conn:
        return conn.execute(
            text(
                "SELECT cell_id, label, confidence, model_version_id, user_id FROM pillar_label "
                "WHERE survey_id = :s AND source = :src ORDER BY cell_id"
            ),
            {"s": survey_id, "src": source},
        ).all()


def test_new_model_labels_replace_the_old_and_leave_human_ones(
    engine: Engine, survey_id: int
) -> None:
    with Session(engine) as session:
        version, _ = model_version_for(session, session.get(Survey, survey_id), None)
    with engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO pillar_label (survey_id, cell_id, label, source, version, "
                "created_at, updated_at) VALUES (:s, 5, 2, 'human', 1, :t, :t)"
            ),
            {"s": survey_id, "t": "2024-01-01 00:00:00.000000"},
        )
    first = np.arange(1, 1001, dtype=np.int64)
    store_model_labels(engine, survey_id, first, first % 4, np.full(1000, 0.5), version.id, None, 1)
    assert len(model_rows(engine, survey_id)) == 1000
    written = store_model_labels(
        engine,
        survey_id,
        np.array([5, 7]),
        np.array([3, 1]),
        np.array([0.9, 0.6]),
        version.id,
        None,
        2,
    )
    assert written == 2
    assert model_rows(engine, survey_id) == [
        (5, 3, pytest.approx(0.9), version.id, None),
        (7, 1, pytest.approx(0.6), version.id, None),
    ]
    assert [r[:2] for r in model_rows(engine, survey_id, "human")] == [(5, 2)]
    with Session(engine) as session:
        labelled = session.exec(
            select(AuditEvent).where(AuditEvent.action == "pillar.model_labels")
        ).all()
        model = session.exec(select(PillarLabel).where(PillarLabel.source == "model")).first()
        assert abs(model.updated_at - utcnow()) < timedelta(minutes=5)  # ORM reads our times
    assert [e.payload["pillars"] for e in labelled] == [1000, 2]


def test_the_model_version_row(engine: Engine, settings: Settings, survey_id: int) -> None:
    with Session(engine) as session:
        survey = session.get(Survey, survey_id)

        def chosen(model_id: int | None):
            return model_version_for(session, survey, model_id)[0]

        shipped = chosen(None)
        assert shipped.checkpoint_path == str(DEFAULT_MODEL.resolve())
        assert shipped.pipeline == Pipeline.phantom and shipped.is_promoted
        assert shipped.sensor_kind == "profile"
        assert chosen(None).id == shipped.id
        paper = ensure_shipped_version(session, Pipeline.phantom, PAPER_MODEL, {})
        assert paper.id != shipped.id and not paper.is_promoted
        assert chosen(paper.id).id == paper.id  # by registry id
        assert chosen(None).id == shipped.id  # the promoted one
        guardrail = ensure_shipped_version(session, Pipeline.guardrail, PAPER_MODEL, {})
        for model_id, problem in ((guardrail.id, "is a guardrail model"), (999, "no model")):
            with pytest.raises(ConfigError, match=problem) as caught:
                chosen(model_id)
            assert caught.value.field == "config.model_id"


def test_jobs_name_models_by_id_never_by_path(settings: Settings) -> None:
    assert parse_config({"model_id": 3, "dense": False}, settings).model_id == 3
    for config, field in (
        ({"model_path": "models/phantom/phantom_cnn.pt"}, "config.model_path"),
        ({"model_id": 0}, "config.model_id"),
        ({"model_id": 2**70}, "config.model_id"),
        ({"model_id": "models/phantom/phantom_cnn.pt"}, "config.model_id"),
    ):
        with pytest.raises(ConfigError) as caught:
            parse_config(config, settings)
        assert caught.value.field == field
    with pytest.raises(ConfigError, match=r"registry id \(config.model_id, see GET /models\)"):
        parse_config({"model_path": "x.pt"}, settings)


def test_tile_progress_rises_through_the_tiles() -> None:
    seen: list[float] = []

    class Context:
        def progress(self, fraction: float, message: str = "") -> None:
            seen.append(fraction)

    report = tile_progress(Context())
    for f in np.linspace(0, 1, 11):
        report(f"tile {int(f * 4) + 1} of 4", f)
    assert seen == sorted(seen)
    assert seen[0] == TILES_PROGRESS[0] and seen[-1] == TILES_PROGRESS[1] < INGEST_AT < 1


def test_a_run_needs_a_survey(engine: Engine, settings: Settings, tmp_path: Path) -> None:
    context = job_context(settings, engine, 1, None)
    with pytest.raises(ConfigError) as caught:
        run_phantom(context, {})
    assert caught.value.field == "survey_id"
