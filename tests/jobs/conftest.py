"""Job fixtures: settings on a temporary data dir, a migrated engine, and task contexts built by
hand (task functions are called directly, without a worker process)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from sqlalchemy.engine import Engine

from app.core.settings import Settings
from app.jobs.registry import JobContext
from app.store.db import init_db, make_engine
from tests.jobs.guardrail_street import jobs, sim_dir  # noqa: F401  (guardrail street fixtures)


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(data_dir=tmp_path / "var", sample_dir=None)


@pytest.fixture
def engine(settings: Settings) -> Iterator[Engine]:
    engine = make_engine(settings.database_url)
    init_db(engine)
    yield engine
    engine.dispose()


def job_context(
    settings: Settings,
    engine: Engine | None,
    job_id: int,
    survey_id: int | None,
    user_id: int | None = None,
    progress: Callable[[float, str], object] | None = None,
) -> JobContext:
    """The context a worker would give job `job_id` (its workdir created); `progress` sees
    every report, and the job is never cancelled."""
    workdir = settings.jobs_dir / str(job_id)
    workdir.mkdir(parents=True, exist_ok=True)

    def report(fraction: float, message: str) -> bool:
        if progress is not None:
            progress(fraction, message)
        return False

    return JobContext(
        job_id=job_id,
        survey_id=survey_id,
        user_id=user_id,
        engine=engine,
        settings=settings,
        workdir=workdir,
        log=logging.getLogger(f"test-job-{job_id}"),
        report_progress=report,
    )


def clutter_street(root: Path, weights_dir: Path) -> dict:
    """A 7-frame simulated street registered in a fresh store under `root` and run through
    `run:clutter`: {"context", "result", "survey", "settings"} (the clutter job tests' runs)."""
    from sqlmodel import Session

    from app.io import open_survey
    from app.jobs.registry import task_for
    from app.simulate.survey import SimulationConfig, simulate
    from app.store.surveys import register_opened_survey

    simulate(SimulationConfig(scene="urban", length=6.0, seed=3), root / "sim")
    settings = Settings(data_dir=root / "var", weights_dir=weights_dir)
    engine = make_engine(settings.database_url)
    init_db(engine)
    survey = open_survey(root / "sim", "sim")
    with Session(engine) as session:
        record = register_opened_survey(
            session, survey, format="sim", source_path=(root / "sim").resolve()
        )
    context = job_context(settings, engine, 1, record.id)
    result = task_for("run:clutter")(context, {"threads": 2})
    return {"context": context, "result": result, "survey": survey, "settings": settings}
