"""The labelling view's display and selection tools on a real viser server and a wire client:
colour by height / intensity, a height slice that hides a canopy (and keeps it out of
selections), top and side views of the focus, standard views, and a large rectangle that is
previewed and written only on Enter."""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from sqlmodel import Session
from viser import SceneClickEvent, SceneNodeDragEvent, SceneRectSelectEvent

from app.io import open_survey
from app.io.ply import write_ply
from app.store.models import LabelSource
from app.store.pillar_labels import STORE_GRID
from app.store.pillar_reads import label_counts, labels_in_box
from app.store.surveys import register_opened_survey
from app.viewer.colour_modes import HEIGHT, INTENSITY, height_colors, intensity_colors
from app.viewer.modes.pillar_selection import CONFIRM_ABOVE, PREVIEW_RGB
from app.viewer.modes.pillars import BRUSH, FILL, INSPECT, MEASURE, POLYGON, PillarMode
from app.viewer.picking import ScreenCamera
from tests.viewer.test_modes_common import (
    Connection,
    Driver,
    add_users,
    new_engine,
    viewer_settings,
)
from tests.viewer.wire import gui_set, is_color_update, is_point_cloud

CANOPY_Z = 6.0  # metres above the ground


@pytest.fixture(scope="module")
def opened(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Connection, Any, int]]:
    """A 40 x 20 m flat street (0.25 m grid, intensity growing eastwards) under a 10 x 10 m
    canopy at 6 m, opened by an annotator in the pillar mode."""
    root = tmp_path_factory.mktemp("pillar-display")
    settings = viewer_settings(root)
    engine = new_engine(settings)
    users = add_users(engine)
    gx, gy = np.meshgrid(np.arange(0, 40, 0.25), np.arange(0, 20, 0.25), indexing="ij")
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    cx, cy = np.meshgrid(np.arange(15, 25, 0.25), np.arange(5, 15, 0.25), indexing="ij")
    canopy = np.stack([cx.ravel(), cy.ravel(), np.full(cx.size, CANOPY_Z)], axis=1)
    xyz = np.concatenate([ground, canopy]) + [600_000.0, 5_000_000.0, 80.0]
    intensity = (xyz[:, 0] - 600_000.0).astype(np.float32) / 40.0
    path = write_ply(root / "street.ply", xyz, fields={"intensity": intensity})
    with Session(engine) as session:
        survey = register_opened_survey(
            session, open_survey(path, "ply"), format="ply", source_path=path
        )
    driver = Driver(settings, engine)
    try:
        yield driver.connect(*users["ann"], survey.id), engine, survey.id
    finally:
        driver.close()
        engine.dispose()


def uuid_of(connection: Connection, label: str, kind: str) -> str:
    message = connection.wait(lambda m: m.get("type") == kind and m["props"].get("label") == label)
    return message["uuid"]


def newest_colors(connection: Connection, name: str, since: int) -> np.ndarray:
    message = connection.wait(
        lambda m: m.get("name") == name and (is_color_update(m) or is_point_cloud(m)), since
    )
    colors = (
        message["updates"]["colors"] if is_color_update(message) else message["props"]["colors"]
    )
    return np.asarray(colors).reshape(-1, 3)


def test_shown_points_hold_what_the_clouds_show(opened) -> None:
    """The positions and pillars kept per cloud (clicks and selections read them instead of
    the memory-mapped map) are the map's, point for point, in the order the client got them."""
    connection, _, _ = opened
    mode = connection.mode
    # the tile is drawn when the client's first camera reaches the session, after the overview
    connection.wait(lambda m: is_point_cloud(m) and m.get("name") == f"/{mode.key}/tile")
    for name in ("overview", "tile"):
        shown = mode.shown[name]
        assert len(shown) and shown.xyz.dtype == np.float32 and shown.xyz.flags.c_contiguous
        np.testing.assert_array_equal(shown.xyz, np.asarray(mode.map.xyz[shown.index]))
        np.testing.assert_array_equal(shown.cell, np.asarray(mode.map.cell[shown.index]))
    both = connection.call(mode._shown)
    in_order = np.concatenate([mode.shown_overview, mode.shown_tile])
    np.testing.assert_array_equal(both.index, in_order)


def test_colour_by_height_then_intensity(opened) -> None:
    connection, _, _ = opened
    mode: PillarMode = connection.mode
    menu = uuid_of(connection, "Colour by", "GuiDropdownMessage")
    mark = connection.mark()
    connection.send(gui_set(menu, HEIGHT))
    colors = newest_colors(connection, "/pillars/overview", mark)
    shown = mode.shown_overview
    xyz = np.asarray(mode.map.xyz[shown], dtype=np.float64)
    expected = height_colors(xyz[:, 2] - mode.map.ground.height(xyz[:, :2]))
    assert np.array_equal(colors, expected)
    mark = connection.mark()
    connection.send(gui_set(menu, INTENSITY))
    colors = newest_colors(connection, "/pillars/overview", mark)
    assert np.array_equal(colors, intensity_colors(np.asarray(mode.map.intensity[shown])))
    assert colors[:, 0].min() < colors[:, 0].max()  # the intensity of the file, not grey
    connection.send(gui_set(menu, "Label"))
    connection.call(lambda: None)


def test_height_slice_hides_the_canopy_and_top_side_views_follow(opened) -> None:
    connection, _, _ = opened
    mode: PillarMode = connection.mode
    menu = uuid_of(connection, "Colour by", "GuiDropdownMessage")
    connection.send(gui_set(menu, HEIGHT))  # the canopy and the road in different colours
    connection.call(lambda: None)
    top_before = np.array(mode.top_image.image, copy=True)
    assert (top_before != 255).any()  # the views show the street around the focus
    slider = uuid_of(connection, "Height slice (m)", "GuiMultiSliderMessage")
    mark = connection.mark()
    connection.send(gui_set(slider, (-2.0, 3.0)))
    cloud = connection.wait(lambda m: is_point_cloud(m) and m["name"] == "/pillars/overview", mark)
    z = np.asarray(cloud["props"]["points"]).reshape(-1, 3)[:, 2]
    assert len(z) and z.max() < 3.0  # the canopy is not shown ...
    connection.call(lambda: None)
    assert not np.array_equal(mode.top_image.image, top_before)  # ... nor in the top view
    connection.send(gui_set(slider, (-2.0, 40.0)))
    connection.send(gui_set(menu, "Label"))
    # viser hands GUI updates to the session's thread from its own: wait for both (the later
    # tests share this view), not for a no-op that may be queued before them
    deadline = time.monotonic() + 30.0
    while (mode.height_slice, mode.colour_by) != ((-2.0, 40.0), "Label"):
        assert time.monotonic() < deadline, (mode.height_slice, mode.colour_by)
        time.sleep(0.05)
    connection.call(lambda: None)  # the redraw queued with them done


def test_standard_views_swing_the_camera_around_its_focus(opened) -> None:
    connection, _, _ = opened
    group = uuid_of(connection, "View", "GuiButtonGroupMessage")
    for preset, axis, sign in (("Top", 2, 1), ("Side", 1, -1), ("Front", 0, -1)):
        mark = connection.mark()
        connection.send(gui_set(group, preset))
        message = connection.wait(lambda m: m.get("type") == "SetCameraPositionMessage", mark)
        camera = connection.session.client.camera
        offset = np.asarray(message["position"]) - np.asarray(camera.look_at)
        # the drive runs along +x (the PLY has no trajectory): +x is the default heading
        assert sign * offset[axis] > 0.95 * np.linalg.norm(offset), preset


def test_a_large_rectangle_waits_for_enter_and_a_small_one_does_not(opened) -> None:
    connection, engine, survey_id = opened
    mode: PillarMode = connection.mode
    session = connection.session
    connection.call(session.show_preset, "Top")

    def rect(lo: tuple[float, float], hi: tuple[float, float]) -> SceneRectSelectEvent:
        return SceneRectSelectEvent(
            client=session.client, client_id=session.client.client_id,
            screen_min=lo, screen_max=hi, modifier="shift",
        )  # fmt: skip

    def human_count() -> int:
        with Session(engine) as db:
            return sum(label_counts(db, survey_id)["human"])

    mark = connection.mark()
    connection.call(mode.on_rect_select, rect((0.1, 0.1), (0.9, 0.9)))
    assert mode.pending is not None and len(mode.pending.cells) > CONFIRM_ABOVE
    preview = connection.wait(
        lambda m: is_point_cloud(m) and m["name"] == "/pillars/selection", mark
    )
    assert tuple(np.asarray(preview["props"]["colors"]).reshape(-1)[:3]) == PREVIEW_RGB
    assert human_count() == 0  # nothing written before Enter
    connection.call(mode.cancel_pending)
    assert mode.pending is None and human_count() == 0
    connection.call(mode.on_rect_select, rect((0.1, 0.1), (0.9, 0.9)))
    selected = len(mode.pending.cells)
    connection.call(mode.confirm_selection)
    assert human_count() == selected and mode.pending is None
    connection.call(mode.undo)
    # a small rectangle is written at once
    connection.call(mode.on_rect_select, rect((0.49, 0.49), (0.51, 0.51)))
    assert mode.pending is None and 0 < human_count() <= CONFIRM_ABOVE
    connection.call(mode.undo)


def test_a_write_logs_its_answer_time_and_the_views_follow_its_colours(
    opened, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server logs how long it took to answer an interaction (a label write: until its
    colours went out), every one with the setting at 0; the top and side views are redrawn
    after the colours, once the write is done."""
    connection, _, _ = opened
    mode: PillarMode = connection.mode
    session = connection.session
    connection.call(session.show_preset, "Top")
    monkeypatch.setattr(session.viewer.settings, "viewer_log_slower_ms", 0.0)
    event = SceneRectSelectEvent(
        client=session.client, client_id=session.client.client_id,
        screen_min=(0.49, 0.49), screen_max=(0.51, 0.51), modifier="shift",
    )  # fmt: skip
    mark = connection.mark()
    with caplog.at_level(logging.WARNING, logger="app.viewer.timing"):
        future = session.submit(mode.on_rect_select, event)
        assert future is not None
        future.result(60)
        connection.call(lambda: None)  # the views' redraw, queued behind the write, done
    lines = [r.getMessage() for r in caplog.records if r.name == "app.viewer.timing"]
    assert any(re.search(r"on_rect_select answered in \d+ ms", line) for line in lines), lines
    assert not mode.views_due
    top = uuid_of(connection, "Top (drive up)", "GuiImageMessage")
    colours = connection.wait(is_color_update, mark)
    after = mark + next(i for i, m in enumerate(connection.since(mark, bool)) if m is colours)
    connection.wait(lambda m: m.get("type") == "GuiUpdateMessage" and m["uuid"] == top, after)
    connection.call(mode.undo)


def click_at(connection: Connection, local: np.ndarray) -> SceneClickEvent:
    """A click whose ray runs from the camera through a local point."""
    client = connection.session.client
    origin = np.asarray(client.camera.position, dtype=np.float64)
    return SceneClickEvent(
        client=client, client_id=client.client_id,
        ray_origin=tuple(origin.tolist()),
        ray_direction=tuple((np.asarray(local, dtype=np.float64) - origin).tolist()),
        screen_pos=((0.5, 0.5),), modifier=None,
    )  # fmt: skip


def stored(engine, survey_id: int) -> dict[int, int]:
    """cell id -> human label of the survey."""
    box = (599_900.0, 4_999_900.0, 600_100.0, 5_000_100.0)
    with Session(engine) as db:
        tile = labels_in_box(db, survey_id, box, LabelSource.human)
    return dict(zip(tile.cell_id.tolist(), tile.label.tolist(), strict=True))


def test_fill_polygon_measure_inspect_and_class_locks(opened) -> None:
    connection, engine, survey_id = opened
    mode: PillarMode = connection.mode
    session = connection.session
    connection.call(session.show_preset, "Top")
    assert stored(engine, survey_id) == {}

    # fill from the road: the flat street under the canopy fills, the canopy (6 m up) not
    connection.call(mode._pick_tool, FILL)
    connection.call(mode.on_click, click_at(connection, np.array([2.0, 2.0, 0.0])))
    assert mode.pending is not None and "fill" in mode.pending.how
    filled = mode.pending.cells
    connection.call(mode.confirm_selection)
    labels = stored(engine, survey_id)
    assert len(labels) == len(filled) and set(labels.values()) == {0}  # ground
    connection.call(mode.undo)

    # polygon: three vertices on the road, Enter closes it; small ones are written at once
    connection.call(mode._pick_tool, POLYGON)
    for corner in ([1.0, 1.0, 0.0], [3.0, 1.0, 0.0], [2.0, 3.0, 0.0]):
        connection.call(mode.on_click, click_at(connection, np.array(corner)))
    assert len(mode.polygon) == 3 and "polygon" in mode.marks
    connection.call(mode.confirm_selection)
    labels = stored(engine, survey_id)
    centres = STORE_GRID.cell_center(*STORE_GRID.decode(np.array(list(labels))))
    local = centres - mode.map.origin[:2]
    assert 20 < len(labels) < 80  # a 2 m^2 triangle of 0.04 m^2 pillars, those with points
    assert (local.min(axis=0) > 0.5).all() and (local.max(axis=0) < 3.5).all()
    assert not mode.polygon and "polygon" not in mode.marks

    # "Apply to: only ground": a brush of phantom over the labelled triangle and the
    # unlabelled road around it relabels only the triangle
    connection.call(mode._pick_tool, BRUSH)
    connection.call(mode._pick, "Phantom")
    mode.apply_to.value = "Only ground"
    mode.radius.value = 2.5  # over the whole triangle
    connection.call(mode.on_click, click_at(connection, np.array([2.0, 2.0, 0.0])))
    after = stored(engine, survey_id)
    assert set(after) == set(labels) and set(after.values()) == {3}
    mode.apply_to.value = "Unlabelled only"  # now the triangle is locked, the road is not
    connection.call(mode._pick, "Ground")
    connection.call(mode.on_click, click_at(connection, np.array([2.0, 2.0, 0.0])))
    final = stored(engine, survey_id)
    assert all(final[c] == 3 for c in labels) and len(final) > len(labels)
    mode.apply_to.value = "All pillars"
    mode.radius.value = 1.0
    assert "brush_ring" in mode.marks

    # measure and inspect
    connection.call(mode._pick_tool, MEASURE)
    connection.call(mode.on_click, click_at(connection, np.array([2.0, 2.0, 0.0])))
    connection.call(mode.on_click, click_at(connection, np.array([20.0, 10.0, CANOPY_Z])))
    assert "Distance **" in mode.status.content and "vertical +6.00 m" in mode.status.content
    # the side view is now the cross-section along the measured line
    assert mode.section is not None and mode.side_image.label.startswith("Section along")
    connection.call(mode._pick_tool, INSPECT)
    connection.call(mode.on_click, click_at(connection, np.array([20.0, 10.0, CANOPY_Z])))
    text = mode.status.content
    assert "+6.00 m above the ground" in text and "intensity 0.5" in text
    connection.call(mode.show_shortcuts)
    modal = connection.wait(lambda m: m.get("type") == "GuiModalMessage")
    assert modal["title"] == "Keyboard shortcuts"


def test_a_free_hand_lasso_labels_what_it_encircles(opened) -> None:
    """Ctrl-drag on the map (caught by the invisible plane under it): the path is drawn while
    it grows, and at release the pillars inside it, as the user sees them, are labelled; a
    path that encloses nothing is dropped."""
    connection, engine, survey_id = opened
    mode: PillarMode = connection.mode
    session = connection.session
    connection.call(session.show_preset, "Top")
    catch = connection.wait(lambda m: m.get("name") == "/pillars/lasso_catch", 0)
    assert catch["props"]["opacity"] == 0.0  # invisible, but drags start on it
    before = stored(engine, survey_id)
    screen = ScreenCamera.of(session.client.camera)
    size = np.array([screen.width, screen.height], dtype=np.float64)
    # a hand-drawn loop round (30, 5)-(34, 5)-(32, 9): many small steps, as the pointer moves
    corners = np.array([[30.0, 5.0, 0.0], [34.0, 5.0, 0.0], [32.0, 9.0, 0.0], [30.0, 5.0, 0.0]])
    edges = zip(corners[:-1], corners[1:], strict=True)
    path = np.concatenate([np.linspace(a, b, 12, endpoint=False) for a, b in edges])
    pixels, _ = screen.project(path)
    positions = [tuple((p / size).tolist()) for p in pixels]

    def drag(phase: str, k: int) -> SceneNodeDragEvent:
        return SceneNodeDragEvent(
            client=session.client, client_id=session.client.client_id, target=mode.catch,
            phase=phase, instance_index=None, start_position=tuple(path[0].tolist()),
            start_screen_pos=positions[0], end_position=tuple(path[k].tolist()),
            end_screen_pos=positions[k], button="left", modifier="cmd/ctrl",
        )  # fmt: skip

    connection.call(mode._pick, "Short object")
    connection.call(mode.on_lasso, drag("start", 0))
    for k in range(1, len(path) - 1):
        connection.call(mode.on_lasso, drag("update", k))
    assert "lasso" in mode.marks  # the path drawn while it grows
    connection.call(mode.on_lasso, drag("end", len(path) - 1))
    assert "lasso" not in mode.marks and not mode.lasso
    labels = {c: v for c, v in stored(engine, survey_id).items() if c not in before}
    centres = STORE_GRID.cell_center(*STORE_GRID.decode(np.array(list(labels))))
    local = centres - mode.map.origin[:2]
    assert 60 < len(labels) < 160  # an 8 m^2 triangle of 0.0625 m^2 pillars with points
    assert set(labels.values()) == {2}  # short object
    assert (local.min(axis=0) > (29.5, 4.5)).all() and (local.max(axis=0) < (34.5, 9.5)).all()
    connection.call(mode.undo)
    # a stroke with no area is dropped, nothing written
    connection.call(mode.on_lasso, drag("start", 0))
    connection.call(mode.on_lasso, drag("end", 0))
    assert "Lasso dropped" in mode.status.content
    assert stored(engine, survey_id) == before
