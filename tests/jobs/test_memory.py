"""A job whose estimated memory exceeds MMSCLEAN_JOB_MEMORY_MB is refused when queued (issue 15,
section 3), naming the config field that needs the most, with the estimate in the message;
configs inside their bounds but too big for the survey are what this catches."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

import tests.jobs.sample_tasks  # noqa: F401  (registers the test:* kinds)
from app.core.errors import ConfigError
from app.core.settings import Settings
from app.jobs.queue import enqueue
from app.jobs.survey_tasks import queue_viewer_map
from app.store.models import Frame, Job, Survey

LIMIT_MB = 2000


@pytest.fixture
def limited(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Settings:
    monkeypatch.setenv("MMSCLEAN_JOB_MEMORY_MB", str(LIMIT_MB))
    return Settings(data_dir=tmp_path / "var", sample_dir=None)


def add_survey(engine: Engine, points: int, frames: int = 10, length: float = 12.0) -> int:
    """A survey row like SemanticKITTI 04's ten frames: `points` over a `length` m drive."""
    with Session(engine) as session:
        survey = Survey(
            name=f"street-{points}", format="semantickitti", source_path="/nowhere",
            frame_count=frames, point_count=points,
        )  # fmt: skip
        session.add(survey)
        session.flush()
        for i, x in enumerate(np.linspace(0.0, length, frames)):
            pose = np.eye(4)
            pose[0, 3] = 500_000.0 + x
            session.add(
                Frame(
                    survey_id=survey.id, frame_index=i, frame_id=f"{i:06d}",
                    point_count=points // frames, pose=pose.ravel().tolist(),
                )
            )  # fmt: skip
        session.commit()
        return survey.id


def refused(engine: Engine, settings: Settings, kind: str, config: dict, survey: int | None):
    with Session(engine) as session:
        with pytest.raises(ConfigError) as caught:
            enqueue(session, kind, config, survey, None, settings)
        assert session.exec(select(Job)).all() == []
    return caught.value


def test_the_limit_is_the_setting(limited: Settings) -> None:
    assert limited.job_memory_mb == LIMIT_MB
    assert Settings(sample_dir=None).job_memory_mb >= 64  # default: half the machine's memory


def test_the_footprint_comes_from_the_frame_rows(engine: Engine) -> None:
    from app.store.surveys import survey_footprint

    survey = add_survey(engine, 1_234_476)
    with Session(engine) as session:
        footprint = survey_footprint(session, survey)
    assert (footprint.points, footprint.frames) == (1_234_476, 10)
    assert footprint.trajectory_max[0] - footprint.trajectory_min[0] == pytest.approx(12.0)


def test_runs_that_fit_are_queued(engine: Engine, limited: Settings) -> None:
    survey = add_survey(engine, 1_234_476)
    with Session(engine) as session:
        for kind, config in (
            ("run:clutter", {}),
            ("run:clutter", {"dufomap_resolution": 0.05, "use_camera": False}),
            ("run:phantom", {}),
            ("run:guardrail", {}),
            ("train:phantom", {}),
        ):
            assert enqueue(session, kind, config, survey, None, limited).id


def test_a_fine_free_space_map_is_refused_with_its_estimate(
    engine: Engine, limited: Settings
) -> None:
    survey = add_survey(engine, 1_234_476)
    error = refused(engine, limited, "run:clutter", {"dufomap_resolution": 0.02}, survey)
    assert error.field == "config.dufomap_resolution"
    message = str(error)
    assert message.startswith("config.dufomap_resolution: this run needs about ")
    assert "survey 1,234,476 points, 10 frames" in message and "0.02 m free-space voxels" in message
    assert message.endswith(f"the limit is {LIMIT_MB:,} MB (MMSCLEAN_JOB_MEMORY_MB)")
    needed = int(re.search(r"needs about ([\d,]+) MB", message).group(1).replace(",", ""))
    assert needed > LIMIT_MB


def test_each_refusal_names_what_grows(engine: Engine, limited: Settings) -> None:
    survey = add_survey(engine, 1_234_476)
    huge = add_survey(engine, 60_000_000, frames=600, length=1200.0)
    dense = add_survey(engine, 60_000_000, frames=600, length=12.0)  # all in one tile
    for kind, config, where, field in (
        (
            "run:clutter",
            {"ground_cell": 0.02, "use_free_space": False},
            survey,
            "config.ground_cell",
        ),
        ("run:clutter", {"use_free_space": False, "use_camera": False}, dense, "survey_id"),
        (
            "run:clutter",
            {"tile_length": 1000.0, "use_camera": False, "use_free_space": False},
            huge,
            "config.tile_length",
        ),
        ("run:phantom", {}, dense, "survey_id"),
        ("run:guardrail", {}, dense, "survey_id"),
        ("train:phantom", {"per_class": 1_000_000}, None, "config.per_class"),
    ):
        error = refused(engine, limited, kind, config, where)
        assert error.field == field, (kind, config, str(error))
    with Session(engine) as session:  # tile by tile, a long survey needs one tile's memory
        assert enqueue(session, "run:phantom", {}, huge, None, limited).id
        no_rays = {"use_camera": False, "use_free_space": False}
        assert enqueue(session, "run:clutter", no_rays, huge, None, limited).id
        # phantom and guardrail tiles are cut shorter where they hold too many points, whatever
        # their length
        assert enqueue(session, "run:phantom", {"tile_length": 1000.0}, huge, None, limited).id
        assert enqueue(session, "run:guardrail", {"tile_length": 1000.0}, huge, None, limited).id
        assert "MMSCLEAN_JOB_MEMORY_MB" in str(error)


def test_a_large_import_queues_the_viewer_map(engine: Engine, limited: Settings) -> None:
    """An imported survey of 5 M points or more gets `prepare:viewer` queued (its first open
    would wait for the map); a smaller one does not (a first open builds it in seconds), nor
    one whose map would not fit the job memory limit (the viewer builds it then)."""
    sizes = {"small": 1_234_476, "large": 60_000_000, "huge": 600_000_000}
    ids = {name: add_survey(engine, points) for name, points in sizes.items()}
    with Session(engine) as session:
        queued = {
            name: queue_viewer_map(session, session.get(Survey, ids[name]), None, limited)
            for name in sizes
        }
        assert queued["small"] is None and queued["huge"] is None
        job = session.get(Job, queued["large"])
        assert job.kind == "prepare:viewer" and job.survey_id == ids["large"]
