"""Guardrail review mode on a real `run:guardrail` of a simulated street with a pipe and a beam
guardrail: slices coloured by their stored label (human brighter), a click toggles the slice
under it through the store with its version (stale: reloaded, nothing written), next uncertain
slice, the adjacency-correction preview and applying it as human labels."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.io import open_survey
from app.jobs.registry import task_for
from app.review.guardrails import preview_correction
from app.simulate.survey import SimulationConfig, simulate
from app.store.audit import audit
from app.store.guardrail_review import SliceLabelEdit, get_slice, next_uncertain, put_slice_labels
from app.store.guardrail_runs import latest_run
from app.store.models import AuditEvent, User
from app.store.surveys import register_opened_survey
from app.viewer.modes.guardrails import (
    FOCUS_BOX_RGB,
    FOCUS_SCALE,
    LABEL_RGB,
    PREVIEW_RGB,
    GuardrailMode,
)
from app.viewer.picking import click_angle, pick_on_ray
from tests.jobs.conftest import job_context
from tests.viewer.test_modes_common import (
    SCENE_POINTS,
    Connection,
    Driver,
    add_users,
    new_engine,
    viewer_settings,
)
from tests.viewer.wire import click_message, is_color_update, is_point_cloud


@dataclass
class Street:
    driver: Driver
    engine: Engine
    survey_id: int
    users: dict[str, tuple[int, str]]


def guardrail_street(root: Path) -> tuple[Driver, Engine, int, dict[str, tuple[int, str]]]:
    """A 30 m simulated street run through `run:guardrail` (geometry head) in a fresh store."""
    sim = root / "sim"
    simulate(
        SimulationConfig(scene="urban", length=30.0, seed=7, scanner="profile", camera=False), sim
    )
    settings = viewer_settings(root)
    engine = new_engine(settings)
    users = add_users(engine)
    with Session(engine) as session:
        record = register_opened_survey(
            session, open_survey(sim, "sim"), format="sim", source_path=sim
        )
    task_for("run:guardrail")(job_context(settings, engine, 1000, record.id), {"head": "geometry"})
    return Driver(settings, engine), engine, record.id, users


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Street]:
    driver, engine, survey_id, users = guardrail_street(tmp_path_factory.mktemp("guardrail-mode"))
    yield Street(driver, engine, survey_id, users)
    driver.close()
    engine.dispose()


SELECTED_POINTS = "/guardrails/selected/points"


def open_mode(street: Street, user: str) -> tuple[Connection, GuardrailMode]:
    connection = street.driver.connect(*street.users[user], street.survey_id)
    return connection, connection.switch("Guardrail review")


def slices_colors(connection: Connection) -> np.ndarray:
    newest = None
    for message in connection.since(0, lambda m: True):
        if is_point_cloud(message) and message["name"] == "/guardrails/slices":
            newest = message["props"]["colors"]
        elif is_color_update(message) and message["name"] == "/guardrails/slices":
            newest = message["updates"]["colors"]
    assert newest is not None
    return np.asarray(newest).reshape(-1, 3)


def shows(connection: Connection, points: np.ndarray, rgb: np.ndarray, timeout: float = 10.0):
    """Wait until the client's slice colours give `points` (a mask of the shown points) `rgb`
    (the recolouring may still be on the wire when the session's call returns)."""
    deadline = time.monotonic() + timeout
    while not (slices_colors(connection)[points] == rgb).all():
        assert time.monotonic() < deadline, f"the client never showed {rgb}"
        time.sleep(0.05)


def row_of(mode: GuardrailMode, slice_id: int) -> int:
    return int(np.searchsorted(mode.rows.id, slice_id))


def click_slice(connection: Connection, mode: GuardrailMode, k: int) -> None:
    """A click straight down onto the highest shown point of stage slice k (through the wire),
    waiting until the session has handled it."""
    xyz = mode.xyz[mode.shown]
    slice_of = mode.point_slice[mode.shown]
    down = np.array([0.0, 0.0, -1.0])
    for top in sorted(np.flatnonzero(slice_of == k), key=lambda i: -xyz[i, 2]):
        origin = xyz[top].astype(np.float64) + np.array([0.0, 0.0, 20.0])
        angle = click_angle(connection.session.client.camera)
        hit = pick_on_ray(xyz, origin, down, angle, mode.point_size.value)
        if hit >= 0 and slice_of[hit] == k:
            break
    else:
        raise AssertionError(f"no click from above reaches slice {k}")
    mark = connection.mark()
    connection.send(click_message(tuple(origin.tolist()), (0.0, 0.0, -1.0)))
    connection.wait(lambda m: is_color_update(m) or m.get("type") == "GuiUpdateMessage", mark)
    time.sleep(0.2)
    connection.call(lambda: None)  # the click's work has finished


def middle_guardrail_slice(mode: GuardrailMode) -> int:
    """A stage slice labelled guardrail whose neighbours along its component are too."""
    s, rows = mode.stage.slices, mode.rows
    label = np.where(mode.row_of_slice >= 0, rows.label[np.maximum(mode.row_of_slice, 0)], -1)
    pairs = zip(s.component.tolist(), s.station_index.tolist(), label.tolist(), strict=True)
    key = {(c, i): lab for c, i, lab in pairs}
    for k in np.flatnonzero(label == 1):
        c, i = int(s.component[k]), int(s.station_index[k])
        shown = (mode.point_slice[mode.shown] == k).any()
        if shown and key.get((c, i - 1)) == 1 and key.get((c, i + 1)) == 1:
            return int(k)
    raise AssertionError("no guardrail slice inside a guardrail run")


def test_slices_are_coloured_by_label_and_a_click_toggles_one(street: Street) -> None:
    connection, mode = open_mode(street, "ann")
    cloud = connection.wait(lambda m: is_point_cloud(m) and m["name"] == "/guardrails/slices")
    points = np.asarray(cloud["props"]["points"])
    assert points.dtype == np.float32 and 0 < len(points) // 3 <= SCENE_POINTS
    slice_of = mode.point_slice[mode.shown]
    rows = mode.row_of_slice[slice_of]
    assert (rows >= 0).all()  # the stage and the store hold the same slices
    expected = LABEL_RGB[mode.rows.label[rows], mode.rows.human[rows].astype(int)]
    assert np.array_equal(slices_colors(connection), expected)
    assert (mode.rows.label[rows] == 1).any() and (mode.rows.label[rows] == 0).any()

    k = middle_guardrail_slice(mode)
    r = int(mode.row_of_slice[k])
    slice_id, version = int(mode.rows.id[r]), int(mode.rows.version[r])
    click_slice(connection, mode, k)
    with Session(street.engine) as session:
        stored = get_slice(session, street.survey_id, slice_id)
    assert stored.label == 0 and stored.version == version + 1
    assert stored.labelled_by == street.users["ann"][0]
    assert mode.focus == k  # the clicked slice is the selected one
    mine = slice_of == k
    shows(connection, mine, LABEL_RGB[0, 1])  # other, by a human: bright
    click_slice(connection, mode, k)  # and back
    with Session(street.engine) as session:
        stored = get_slice(session, street.survey_id, slice_id)
    assert stored.label == 1 and stored.version == version + 2
    shows(connection, mine, LABEL_RGB[1, 1])


def test_a_stale_toggle_is_refused_and_reloaded(street: Street) -> None:
    connection, mode = open_mode(street, "ann")
    k = int(np.flatnonzero(mode.row_of_slice >= 0)[0])
    r = int(mode.row_of_slice[k])
    slice_id, held = int(mode.rows.id[r]), int(mode.rows.version[r])
    label = int(mode.rows.label[r])
    with Session(street.engine) as session:
        rev = session.get(User, street.users["rev"][0])
        put_slice_labels(session, street.survey_id, [SliceLabelEdit(slice_id, held, 1)], rev)

    def stale_toggle() -> None:  # on the session's thread: no live reload in between
        mode.rows.version[r], mode.rows.label[r] = held, label  # as if not seen yet
        mode.toggle_slice(k)

    mark = connection.mark()
    connection.call(stale_toggle)
    connection.wait(lambda m: m.get("type") == "NotificationShowMessage", mark)
    with Session(street.engine) as session:
        stored = get_slice(session, street.survey_id, slice_id)
    assert stored.label == 1 and stored.labelled_by == street.users["rev"][0]
    assert stored.version == held + 1 == mode.rows.version[row_of(mode, slice_id)]
    assert mode.rows.label[row_of(mode, slice_id)] == 1 and mode.rows.human[row_of(mode, slice_id)]


def test_next_uncertain_slice_flies_there(street: Street) -> None:
    connection, mode = open_mode(street, "ann")
    with Session(street.engine) as session:
        row, remaining = next_uncertain(session, street.survey_id)
    mark = connection.mark()
    connection.call(mode.next_uncertain_slice)
    s = mode.stage.slices
    assert mode.focus is not None
    assert (s.component[mode.focus], s.station_index[mode.focus]) == (
        row.component_id,
        row.slice_index,
    )
    mine = mode.point_slice[mode.shown] == mode.focus
    xyz = mode.xyz[mode.shown[mine]].astype(np.float64)
    centre = s.centre[mode.focus] - mode.origin
    target = xyz[np.argmin(((xyz - centre) ** 2).sum(axis=1))]
    connection.wait(  # the camera looks at the slice's shown point nearest its centre
        lambda m: (
            m.get("type") == "SetCameraLookAtMessage"
            and np.allclose(m["look_at"], target, atol=1e-3)
        ),
        mark,
    )
    assert f"{remaining:,} unlabelled left" in mode.status.content
    # the slice is selected: its points drawn large in their own colour inside a red box
    assert mine.any()
    cloud = connection.wait(lambda m: is_point_cloud(m) and m["name"] == SELECTED_POINTS, mark)
    assert len(cloud["props"]["points"]) // 3 == int(mine.sum())
    assert cloud["props"]["point_size"] == pytest.approx(FOCUS_SCALE * mode.point_size.value)
    own = np.asarray(cloud["props"]["colors"]).reshape(-1, 3)
    assert np.array_equal(own, slices_colors(connection)[mine])  # its label stays readable
    box = connection.wait(lambda m: m.get("type") == "BoxMessage", mark)
    assert box["name"] == "/guardrails/selected/box" and box["props"]["wireframe"]
    assert tuple(box["props"]["color"]) == FOCUS_BOX_RGB
    extent = np.ptp(mode.xyz[mode.shown[mine]], axis=0)
    assert np.all(np.asarray(box["props"]["dimensions"]) > extent)  # around every point


def test_preview_shows_the_correction_and_apply_writes_it(street: Street) -> None:
    connection, mode = open_mode(street, "rev")
    k = middle_guardrail_slice(mode)
    connection.call(mode.toggle_slice, k)  # a hole in a guardrail: the correction fills it
    slice_id = int(mode.rows.id[mode.row_of_slice[k]])
    connection.call(mode.preview_correction)
    with Session(street.engine) as session:
        direct = preview_correction(session, street.survey_id, {})
    expected = {
        s["id"]: s["corrected_label"]
        for s in direct["slices"]
        if s["corrected_label"] != s["label"]
    }
    assert mode.preview == expected and expected.get(slice_id) == 1
    assert not mode.apply.disabled and f"({len(expected)} slices)" in mode.apply.label
    mine = mode.point_slice[mode.shown] == k
    shows(connection, mine, PREVIEW_RGB[1])

    connection.call(mode.apply_correction)
    with Session(street.engine) as session:
        for sid, label in expected.items():
            stored = get_slice(session, street.survey_id, sid)
            assert stored.label == label and stored.labelled_by == street.users["rev"][0]
    assert mode.preview == {} and mode.apply.disabled
    shows(connection, mine, LABEL_RGB[1, 1])
    connection.call(mode.preview_correction)  # nothing left to correct
    assert mode.preview == {} and mode.apply.disabled


def test_labels_by_someone_else_recolour_live(street: Street) -> None:
    """Another user labels a slice straight through the store: the mode's rows and the
    client's colours follow within seconds; a new run (its ingest event) reloads the mode."""
    connection, mode = open_mode(street, "ann")
    slice_of = mode.point_slice[mode.shown]
    k = int(next(k for k in np.unique(slice_of) if mode.row_of_slice[k] >= 0))
    r = int(mode.row_of_slice[k])
    slice_id, version, label = int(mode.rows.id[r]), int(mode.rows.version[r]), mode.rows.label[r]
    new = 1 - int(label)
    with Session(street.engine) as session:
        rev = session.get(User, street.users["rev"][0])
        put_slice_labels(session, street.survey_id, [SliceLabelEdit(slice_id, version, new)], rev)
    deadline = time.monotonic() + 10
    while mode.rows.version[row_of(mode, slice_id)] != version + 1:
        assert time.monotonic() < deadline, "the mode never saw the other label"
        time.sleep(0.05)
    assert mode.rows.label[row_of(mode, slice_id)] == new and mode.rows.human[r]
    shows(connection, slice_of == k, LABEL_RGB[new, 1])

    mark = connection.mark()
    with Session(street.engine) as session:  # the same run ingested again, as a new one
        run = session.get(AuditEvent, latest_run(session, street.survey_id).event_id)
        audit(session, None, run.action, "survey", street.survey_id, **run.payload)
        session.commit()
    connection.reloaded(mode)
    assert isinstance(connection.mode, GuardrailMode) and "slices" in connection.mode.clouds
    connection.wait(lambda m: is_point_cloud(m) and m["name"] == "/guardrails/slices", mark)
    assert not connection.since(mark, lambda m: m.get("type") == "SetCameraLookAtMessage")
