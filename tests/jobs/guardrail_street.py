"""The guardrail jobs' test street: a short simulated street with a pipe and a beam guardrail
(synthetic), one survey and two users in a fresh database; `Jobs.context()` builds the context
a worker would give the next job, so tasks are called directly."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlmodel import Session

from app.core.settings import Settings
from app.jobs.registry import JobContext, task_for
from app.simulate.survey import SimulationConfig, simulate
from app.store.db import init_db, make_engine
from app.store.models import Job, JobStatus, Role, Survey, User

# the geometry head without camera images keeps a run at a few seconds; 20 m tiles: the 30 m
# street runs as two, so the review's stage is read from two tiles' parts
CONFIG = {"head": "geometry", "tile_length": 20}


def simulate_street(root: Path) -> Path:
    """The simulated street's survey folder under `root`."""
    out = root / "sim"
    simulate(
        SimulationConfig(scene="urban", length=30.0, seed=7, scanner="profile", camera=False), out
    )
    return out


class Jobs:
    """A database with one survey and two users; `context()` makes the next job's context."""

    def __init__(self, root: Path, sim_dir: Path):
        self.settings = Settings(data_dir=root / "var", sample_dir=None)
        self.engine = make_engine(self.settings.database_url)
        init_db(self.engine)
        with Session(self.engine, expire_on_commit=False) as session:
            survey = Survey(name="street", format="sim", source_path=str(sim_dir))
            annotator = User(username="ann", hashed_password="-", role=Role.annotator)
            reviewer = User(username="rev", hashed_password="-", role=Role.reviewer)
            session.add_all([survey, annotator, reviewer])
            session.commit()
            self.survey_id, self.annotator, self.reviewer = survey.id, annotator, reviewer
        self.progress: list[tuple[int, float, str]] = []

    def context(self, kind: str) -> JobContext:
        with Session(self.engine) as session:
            job = Job(
                kind=kind,
                survey_id=self.survey_id,
                created_by=self.reviewer.id,
                status=JobStatus.running,
            )
            session.add(job)
            session.commit()
            job_id = job.id
        workdir = self.settings.jobs_dir / str(job_id)
        workdir.mkdir(parents=True)
        return JobContext(
            job_id=job_id,
            survey_id=self.survey_id,
            user_id=self.reviewer.id,
            engine=self.engine,
            settings=self.settings,
            workdir=workdir,
            log=logging.getLogger("test-guardrail-job"),
            report_progress=lambda f, m: self.progress.append((job_id, f, m)) and False,
        )

    def run(self, config: dict | None = None) -> dict:
        context = self.context("run:guardrail")
        return task_for("run:guardrail")(context, {**CONFIG, **(config or {})})

    def rebuild(self, config: dict | None = None) -> dict:
        return task_for("guardrail:rebuild")(self.context("guardrail:rebuild"), config or {})

    def session(self) -> Session:
        return Session(self.engine, expire_on_commit=False)


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The street, simulated once per test module."""
    return simulate_street(tmp_path_factory.mktemp("guardrail-jobs"))


@pytest.fixture
def jobs(tmp_path: Path, sim_dir: Path) -> Iterator[Jobs]:
    """A store and job helpers of their own per test, over the shared street."""
    jobs = Jobs(tmp_path, sim_dir)
    yield jobs
    jobs.engine.dispose()
