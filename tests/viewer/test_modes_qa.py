"""QA mode on real jobs run through the worker's own code path in-process (`run:clutter`,
`run:phantom`, `clutter:recompute` on a small simulated street): the original / cleaned toggle,
removed points red, the metrics panel from the newest jobs' results, the export links."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from scipy.spatial import cKDTree
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.core.settings import Settings
from app.io import open_survey
from app.io.las import read_las_points
from app.jobs.queue import enqueue
from app.jobs.registry import load_tasks
from app.jobs.worker import run_job
from app.simulate.survey import SimulationConfig, simulate
from app.store.clutter_review import DecisionWrite, decide, list_instances
from app.store.jobs import claim_next
from app.store.models import Decision, Job, JobStatus
from app.store.surveys import register_opened_survey
from app.viewer.modes.qa import CLEANED, ORIGINAL, REMOVED_RGB, QAMode, percent
from tests.pipelines.clutter.conftest import weights_dir  # noqa: F401  (the fixture)
from tests.viewer.test_modes_common import (
    SCENE_POINTS,
    Connection,
    Driver,
    add_users,
    new_engine,
    viewer_settings,
)
from tests.viewer.wire import is_color_update, is_point_cloud


@dataclass
class Street:
    driver: Driver
    engine: Engine
    settings: Settings
    survey_id: int
    users: dict[str, tuple[int, str]]
    jobs: dict[str, Job]


def run_queued(
    engine: Engine, settings: Settings, survey_id: int, user_id: int, kind: str, config: dict
) -> Job:
    """Queue a job and run it as a worker would (claim, run, finish), in this process."""
    with Session(engine) as session:
        queued = enqueue(session, kind, config, survey_id, user_id, settings)
    job = claim_next(engine, os.getpid())
    assert job is not None and job.id == queued.id
    assert run_job(engine, settings, job, load_tasks(), os.getppid()) == JobStatus.succeeded
    with Session(engine) as session:
        return session.get(Job, job.id)


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory, weights_dir: Path) -> Iterator[Street]:  # noqa: F811
    root = tmp_path_factory.mktemp("qa-mode")
    simulate(SimulationConfig(scene="urban", length=6.0, seed=3), root / "sim")
    settings = viewer_settings(root, weights_dir=weights_dir, workers=1)
    engine = new_engine(settings)
    users = add_users(engine)
    with Session(engine) as session:
        record = register_opened_survey(
            session, open_survey(root / "sim", "sim"), format="sim", source_path=root / "sim"
        )
    rev = users["rev"][0]
    jobs = {
        kind: run_queued(engine, settings, record.id, rev, kind, config)
        for kind, config in (("run:phantom", {}), ("run:clutter", {"threads": 2}))
    }
    driver = Driver(settings, engine)
    yield Street(driver, engine, settings, record.id, users, jobs)
    driver.close()
    engine.dispose()


def open_mode(street: Street) -> tuple[Connection, QAMode]:
    connection = street.driver.connect(*street.users["rev"], street.survey_id)
    return connection, connection.switch("QA")


def cloud(connection: Connection, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(points, newest colours) of a cloud the client holds."""
    connection.wait(lambda m: is_point_cloud(m) and m["name"] == name)
    points = colors = None
    for message in connection.since(0, lambda m: True):
        if is_point_cloud(message) and message["name"] == name:
            points = np.asarray(message["props"]["points"]).reshape(-1, 3)
            colors = message["props"]["colors"]
        elif is_color_update(message) and message["name"] == name:
            colors = message["updates"]["colors"]
    assert points is not None, f"the client has no {name}"
    return points, np.asarray(colors).reshape(-1, 3)


def gui_uuid(connection: Connection, kind: str, label: str) -> str:
    for message in connection.since(0, lambda m: m.get("type") == kind):
        if message["props"]["label"] == label:
            return message["uuid"]
    raise KeyError(label)


def gui_update(uuid: str, value: Any) -> bytes:
    """What the browser sends when a GUI input changes."""
    return msgspec.msgpack.encode(
        {"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": value}}
    )


def visibility(connection: Connection, name: str, since: int) -> bool:
    message = connection.wait(
        lambda m: m.get("type") == "SetSceneNodeVisibilityMessage" and m["name"] == name, since
    )
    return bool(message["visible"])


def file_points(job: Job, which: str, origin: np.ndarray) -> np.ndarray:
    return read_las_points(Path(job.result["files"][which])).xyz - origin


def markdown(connection: Connection) -> str:
    """All markdown the client was sent (once the mode's last one, the exports, arrived)."""
    connection.wait(
        lambda m: m.get("type") == "GuiMarkdownMessage" and "Exports" in m["props"]["_markdown"]
    )
    return "\n".join(
        str(m["props"]["_markdown"])
        for m in connection.since(0, lambda m: m.get("type") == "GuiMarkdownMessage")
    )


def test_original_and_cleaned_maps_with_removed_points_red(street: Street) -> None:
    connection, mode = open_mode(street)
    job = street.jobs["run:clutter"]
    cleaned, _ = cloud(connection, "/qa/cleaned")
    removed, colors = cloud(connection, "/qa/removed")
    assert cleaned.dtype == np.float32 and 0 < len(cleaned) <= SCENE_POINTS
    assert 0 < len(removed) <= SCENE_POINTS
    assert (colors == REMOVED_RGB).all()
    # the points are the job's files, re-centred on the survey origin
    for shown, which in ((cleaned, "cleaned"), (removed, "removed")):
        distance, _ = cKDTree(file_points(job, which, mode.origin)).query(shown, workers=1)
        assert distance.max() < 1e-3
    counts = mode.counts.content
    assert f"{job.result['counts']['map_points']:,}" in counts

    # "Cleaned" hides the removed points, "Original" shows them again (through the wire)
    show = gui_uuid(connection, "GuiDropdownMessage", "Show")
    mark = connection.mark()
    connection.send(gui_update(show, CLEANED))
    assert visibility(connection, "/qa/removed", mark) is False
    mark = connection.mark()
    connection.send(gui_update(show, ORIGINAL))
    assert visibility(connection, "/qa/removed", mark) is True

    # without the highlight the removed points look like the map around them
    highlight = gui_uuid(connection, "GuiCheckboxMessage", "Highlight removed (red)")
    mark = connection.mark()
    connection.send(gui_update(highlight, False))
    connection.wait(lambda m: is_color_update(m) and m["name"] == "/qa/removed", mark)
    _, colors = cloud(connection, "/qa/removed")
    assert not (colors == REMOVED_RGB).all(axis=1).any()
    assert (np.abs(colors[:, 0].astype(int) - colors[:, 1]) <= 1).all()  # grey
    assert colors.max() <= 200  # not washed out on the white background (issue 20)


def run_and_reload(
    street: Street, connection: Connection, mode: QAMode, kind: str, says: Callable[[Job], str]
) -> tuple[Job, QAMode, int]:
    """Run `kind` while QA is open: (the job, the reloaded mode once its panel `says` so about
    the job, the connection's mark from before the run)."""
    mark = connection.mark()
    job = run_queued(
        street.engine, street.settings, street.survey_id, street.users["rev"][0], kind, {}
    )
    mode = connection.reloaded(mode)
    assert isinstance(mode, QAMode)
    text = says(job)
    connection.wait(
        lambda m: m.get("type") == "GuiMarkdownMessage" and text in str(m["props"]["_markdown"]),
        mark,
    )
    return job, mode, mark


def test_metrics_panel_and_export_links(street: Street) -> None:
    connection, _ = open_mode(street)
    text = markdown(connection)
    clutter, phantom = street.jobs["run:clutter"], street.jobs["run:phantom"]
    full = clutter.result["metrics"]["full"]
    kinds = list(full)
    assert f"| 360° | {' | '.join(kinds)} |" in text  # one narrow table per scope
    oa = [full[k]["error_matrix"]["overall_accuracy"] for k in kinds]
    assert f"| OA | {' | '.join(map(percent, oa))} |" in text
    aa = [full[k]["scores"]["AA"] for k in kinds]
    assert f"| AA | {' | '.join(map(percent, aa))} |" in text
    widest = max(len(line.split("|")) - 2 for line in text.splitlines() if line.startswith("|"))
    assert widest <= 4  # no table wider than four columns: the side panel is narrow
    assert f"job {clutter.id}" in text and f"job {phantom.id}" in text
    point = phantom.result["metrics"]["point"]["classes"]["phantom"]
    p, r, f = point["precision"], point["recall"], point["f1"]
    assert f"| phantom | {p:.1f} | {r:.1f} | {f:.1f} |" in text
    base = f"/surveys/{street.survey_id}/exports"
    assert f"({base}/qa-report.html)" in text and f"({base}/cleaned.laz)" in text


def test_the_newest_clutter_job_is_shown(street: Street) -> None:
    """After a review and `clutter:recompute`, an open QA mode reloads (the job's success
    reaches it through the label feed) and shows the recomputed maps."""
    connection, mode = open_mode(street)
    markdown(connection)
    with Session(street.engine) as session:
        _, states = list_instances(session, street.survey_id, limit=1000)
        target = max(states, key=lambda s: s.point_count)
        decide(
            session,
            street.survey_id,
            [DecisionWrite(target.id, target.version, Decision.rejected)],
            street.users["rev"][0],
        )
    job, mode, mark = run_and_reload(
        street, connection, mode, "clutter:recompute", lambda j: f"job {j.id}, clutter:recompute"
    )
    connection.wait(lambda m: is_point_cloud(m) and m["name"] == "/qa/removed", mark)
    removed, _ = cloud(connection, "/qa/removed")
    distance, _ = cKDTree(file_points(job, "removed", mode.origin)).query(removed, workers=1)
    assert distance.max() < 1e-3
    assert f"{job.result['counts']['map_points']:,}" in mode.counts.content


def test_a_phantom_run_is_shown_like_a_clutter_run(street: Street) -> None:
    """A phantom run removes points too: when it is the newest, QA shows its cleaned map and
    removed points (it said "No clutter run on this survey yet", issue 20)."""
    connection, mode = open_mode(street)
    markdown(connection)
    job, mode, _ = run_and_reload(
        street, connection, mode, "run:phantom", lambda j: f"Maps from **run:phantom**, job {j.id}"
    )
    total = len(read_las_points(Path(job.result["files"]["cleaned"])).xyz)
    deadline = time.monotonic() + 30
    while f"Cleaned map: {total:,} points" not in mode.counts.content:  # its maps are loaded
        assert time.monotonic() < deadline, mode.counts.content
        time.sleep(0.05)
    cleaned = np.asarray(mode.clouds["cleaned"].points)  # what the scene holds (sent as is)
    distance, _ = cKDTree(file_points(job, "cleaned", mode.origin)).query(cleaned, workers=1)
    assert distance.max() < 1e-3
