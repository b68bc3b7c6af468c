"""The sample survey is registered once, on the first start of an empty database."""

from __future__ import annotations

from pathlib import Path

from sqlmodel import Session, select

from app.api.sample import load_sample_on_first_start
from app.core.settings import Settings
from app.store.db import init_db, make_engine
from app.store.models import Frame, Survey


def test_sample_loaded_once(tmp_path: Path) -> None:
    settings = Settings()
    assert settings.sample_dir is not None and settings.sample_dir.is_dir()
    engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    init_db(engine)
    first = load_sample_on_first_start(engine, settings.sample_dir)
    assert first is not None
    assert load_sample_on_first_start(engine, settings.sample_dir) is None  # second start
    with Session(engine) as session:
        survey = session.exec(select(Survey)).one()
        frames = session.exec(select(Frame).where(Frame.survey_id == survey.id)).all()
    assert survey.format == "sim" and survey.has_reference_labels
    assert len(frames) == survey.frame_count == 59
    assert survey.point_count == sum(f.point_count for f in frames) > 1_000_000
    assert len(frames[0].pose) == 16


def test_no_sample(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("MMSCLEAN_SAMPLE_DIR", "")
    assert Settings().sample_dir is None
    engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    init_db(engine)
    assert load_sample_on_first_start(engine, None) is None
    assert load_sample_on_first_start(engine, tmp_path / "missing") is None
