"""Clutter review mode on a real `run:clutter` of a small simulated street (the real ESPNetv2
weights): the frame's points coloured by the pipeline's flags and the decisions, approve /
reject through the store with versions (a stale one reloads), a click selects the instance
under it, approve-all, next pending frame, recompute queued, read-only for annotators; the panel
width, the selection on the camera image, and shift-drag corrections of an instance's extent
(remove points from it, add a missed object) written through the store and seen by another
client; the camera image in 3D and the Ctrl-drag box on it."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session, select
from viser import SceneNodeDragEvent, SceneRectSelectEvent

from app.core.errors import PermissionDeniedError
from app.io import open_survey
from app.jobs.registry import task_for
from app.review.box_objects import PixelBox, object_in_box
from app.simulate.survey import SimulationConfig, simulate
from app.store.clutter_corrections import frame_corrections
from app.store.clutter_review import DecisionWrite, decide, frame_counts, get_instance
from app.store.models import AuditEvent, Decision, Job, JobStatus
from app.store.surveys import register_opened_survey
from app.viewer.modes.clutter import ADD_OBJECT, RECTANGLE, REMOVE_FROM_INSTANCE, ClutterMode
from app.viewer.modes.clutter_states import (
    APPROVED,
    REJECTED,
    REMOVED_PENDING,
    SELECTED_RGB,
    STATE_RGB,
    point_states,
)
from app.viewer.modes.pillar_selection import rectangle_points
from app.viewer.picking import ScreenCamera, click_angle, pick_on_ray
from tests.jobs.conftest import job_context
from tests.pipelines.clutter.conftest import weights_dir  # noqa: F401  (the fixture)
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
class Review:
    driver: Driver
    engine: Engine
    survey_id: int
    users: dict[str, tuple[int, str]]
    run_dir: Path


@pytest.fixture(scope="module")
def review(tmp_path_factory: pytest.TempPathFactory, weights_dir: Path) -> Iterator[Review]:  # noqa: F811
    """A 6-frame simulated street run through `run:clutter` in a fresh store, and a viewer."""
    root = tmp_path_factory.mktemp("clutter-mode")
    simulate(SimulationConfig(scene="urban", length=6.0, seed=3), root / "sim")
    settings = viewer_settings(root, weights_dir=weights_dir)
    engine = new_engine(settings)
    users = add_users(engine)
    with Session(engine) as session:
        record = register_opened_survey(
            session, open_survey(root / "sim", "sim"), format="sim", source_path=root / "sim"
        )
    context = job_context(settings, engine, 1000, record.id)
    task_for("run:clutter")(context, {"threads": 2})
    driver = Driver(settings, engine)
    yield Review(driver, engine, record.id, users, context.workdir)
    driver.close()
    engine.dispose()


def open_mode(review: Review, user: str) -> tuple[Connection, ClutterMode]:
    connection = review.driver.connect(*review.users[user], review.survey_id)
    return connection, connection.switch("Clutter review")


def cloud_colors(connection: Connection, since: int = 0) -> np.ndarray:
    """The newest colours of the frame cloud the client holds (full message or update)."""
    newest = None
    for message in connection.since(since, lambda m: True):
        if is_point_cloud(message) and message["name"] == "/clutter/frame":
            newest = message["props"]["colors"]
        elif is_color_update(message) and message["name"] == "/clutter/frame":
            newest = message["updates"]["colors"]
    assert newest is not None, "the client has no frame cloud"
    return np.asarray(newest).reshape(-1, 3)


def test_frame_is_coloured_by_the_pipeline_and_decisions_apply_with_versions(
    review: Review,
) -> None:
    connection, mode = open_mode(review, "rev")
    frame_id = mode.frames[mode.frame_index].frame_id
    assert mode.frames[mode.frame_index].pending > 0  # opens on a frame that needs review
    cloud = connection.wait(lambda m: is_point_cloud(m) and m["name"] == "/clutter/frame")
    points = np.asarray(cloud["props"]["points"])
    assert points.dtype == np.float32 and len(points) // 3 == len(mode.shown) <= SCENE_POINTS
    connection.wait(lambda m: m.get("type") == "GuiImageMessage")  # camera and mask images

    # every removed point of the run's membership is orange while pending
    with np.load(review.run_dir / "instances" / f"{frame_id}.npz") as member:
        owner, flags = member["instance"], member["removed"]
    assert np.array_equal(mode.owner, owner) and np.array_equal(mode.flags, flags)
    colors = cloud_colors(connection)
    removed = flags[mode.shown]
    assert removed.any()
    assert (colors[removed] == STATE_RGB[REMOVED_PENDING]).all()
    assert not (colors[~removed] == STATE_RGB[REMOVED_PENDING]).all(axis=1).any()

    # approve the instance with the most points the pipeline kept: they turn red too
    kept_by_pipeline = np.bincount(owner[(owner >= 0) & ~flags], minlength=owner.max() + 1)
    target = mode.by_index[int(np.argmax(kept_by_pipeline))]
    other = next(s for s in mode.states if s.id != target.id and s.point_count > 1)
    mark = connection.mark()
    connection.call(mode.decide, [target], Decision.approved)
    with Session(review.engine) as session:
        stored = get_instance(session, review.survey_id, target.id)
    assert stored.decision == Decision.approved and stored.version == target.version + 1
    assert stored.user_id == review.users["rev"][0]
    connection.wait(lambda m: is_color_update(m) and m["name"] == "/clutter/frame", mark)
    colors = cloud_colors(connection)
    mine = owner[mode.shown] == target.instance_index
    assert mine.any() and (colors[mine] == STATE_RGB[APPROVED]).all()
    assert "approved" in mode.rows[mode.states.index(mode.by_index[target.instance_index])].label
    # ... and red on the camera image, where they project into it (over the tinted masks)
    row, col = mode.pixels
    seen = np.flatnonzero((owner == target.instance_index) & (row >= 0))
    assert len(seen)  # a camera instance
    image, scale = mode._overlay(), mode.photo[1]
    r = np.minimum((row[seen] * scale).astype(int), image.shape[0] - 1)
    c = np.minimum((col[seen] * scale).astype(int), image.shape[1] - 1)
    red = (image[r, c] == STATE_RGB[APPROVED]).all(axis=1)
    assert red.mean() > 0.5  # other instances' dots may share a pixel of the small image

    # reject another: its points are kept (green), the rest of the frame is as the pipeline says
    connection.call(mode.decide, [other], Decision.rejected)
    expected = point_states(
        owner,
        flags,
        np.array([s.instance_index for s in mode.states]),
        [s.decision for s in mode.states],
    )
    assert np.array_equal(mode.state, expected)
    assert (expected[owner == other.instance_index] == REJECTED).all()

    # someone else decides `other` meanwhile: our stale write is refused and we reload
    held = mode.by_index[other.instance_index]
    with Session(review.engine) as session:
        decide(
            session,
            review.survey_id,
            [DecisionWrite(held.id, held.version, Decision.approved)],
            review.users["rev2"][0],
        )
    mark = connection.mark()
    connection.call(mode.decide, [held], Decision.pending)
    with Session(review.engine) as session:
        now = get_instance(session, review.survey_id, held.id)
    assert now.decision == Decision.approved and now.user_id == review.users["rev2"][0]
    assert mode.by_index[other.instance_index].version == now.version  # reloaded
    connection.wait(lambda m: m.get("type") == "NotificationShowMessage", mark)
    assert "first" in mode.status.content


def test_click_selects_the_instance_under_it(review: Review) -> None:
    connection, mode = open_mode(review, "rev")
    shown = mode.shown
    xyz = mode.xyz[shown]
    # a ray straight down onto the highest point of a sizeable instance
    sizes = np.bincount(mode.owner[shown][mode.owner[shown] >= 0])
    instance = int(np.argmax(sizes))
    candidates = np.flatnonzero(mode.owner[shown] == instance)
    top = candidates[np.argmax(xyz[candidates, 2])]
    origin = xyz[top].astype(np.float64) + np.array([0.0, 0.0, 30.0])
    angle = click_angle(connection.session.client.camera)
    down = np.array([0.0, 0.0, -1.0])
    assert pick_on_ray(xyz, origin, down, angle, mode.point_size.value) == top
    connection.send(click_message(tuple(origin.tolist()), (0.0, 0.0, -1.0)))
    deadline = time.monotonic() + 30
    while mode.selected != instance and time.monotonic() < deadline:
        time.sleep(0.05)
    assert mode.selected == instance
    connection.call(lambda: None)  # the selection's redraw has finished
    row = mode.rows[[s.instance_index for s in mode.states].index(instance)]
    assert row.label.startswith("▶ ")
    assert f"#{instance}" in mode.selected_text.content
    # the selected instance is drawn magenta, the others keep their state colours
    colors = mode._colors()
    assert (colors[mode.owner[shown] == instance] == SELECTED_RGB).all()
    assert not (colors[mode.owner[shown] != instance] == SELECTED_RGB).all(axis=1).any()


def test_approve_all_pending_next_pending_and_recompute(review: Review) -> None:
    connection, mode = open_mode(review, "rev")
    first = mode.frame_index
    connection.call(mode.decide_pending, Decision.approved)
    with Session(review.engine) as session:
        counts = {c.frame_id: c for c in frame_counts(session, review.survey_id)}
    assert counts[mode.frames[first].frame_id].pending == 0
    mark = connection.mark()
    connection.call(mode.next_pending)
    assert mode.frame_index != first and mode.frames[mode.frame_index].pending > 0
    cloud = connection.wait(lambda m: is_point_cloud(m) and m["name"] == "/clutter/frame", mark)
    assert len(np.asarray(cloud["props"]["points"])) // 3 == len(mode.shown)
    connection.call(mode.show_frame, first)  # previous frames stay reachable
    assert mode.frame_index == first and mode.frames[first].pending == 0

    connection.call(mode.recompute)
    with Session(review.engine) as session:
        job = session.exec(select(Job).where(Job.kind == "clutter:recompute")).one()
    assert job.status == JobStatus.queued and job.survey_id == review.survey_id
    assert job.created_by == review.users["rev"][0]


def test_annotators_see_but_cannot_decide(review: Review) -> None:
    connection, mode = open_mode(review, "ann")
    assert not mode.all_pending.visible and "Read only" in mode.status.content
    assert all(row.options == ("Select",) for row in mode.rows)
    state = mode.states[0]
    with pytest.raises(PermissionDeniedError):
        connection.call(mode.decide, [state], Decision.rejected)
    with pytest.raises(PermissionDeniedError):
        connection.call(mode.recompute)
    with Session(review.engine) as session:
        assert get_instance(session, review.survey_id, state.id).version == state.version


def test_decisions_by_someone_else_show_up_live(review: Review) -> None:
    """Another reviewer decides an instance of the open frame straight through the store: the
    list, the point states and the client's colours follow within seconds, and the user's own
    selection stays."""
    connection, mode = open_mode(review, "rev")
    shown_owner = mode.owner[mode.shown]
    visible = [s for s in mode.states if (shown_owner == s.instance_index).any()]
    assert len(visible) >= 2
    chosen, target = visible[0], next(s for s in visible[1:] if s.decision != Decision.rejected)
    connection.call(mode.select, chosen.instance_index)
    mark = connection.mark()
    with Session(review.engine) as session:
        decide(
            session,
            review.survey_id,
            [DecisionWrite(target.id, target.version, Decision.rejected)],
            review.users["rev2"][0],
        )
    deadline = time.monotonic() + 10
    while mode.by_index[target.instance_index].decision != Decision.rejected:
        assert time.monotonic() < deadline, "the open frame never saw the other decision"
        time.sleep(0.05)
    connection.call(lambda: None)  # the refresh has finished
    now = mode.by_index[target.instance_index]
    assert now.version == target.version + 1 and now.user_id == review.users["rev2"][0]
    assert mode.selected == chosen.instance_index
    assert "rejected" in mode.rows[mode.states.index(now)].label
    assert (mode.state[mode.owner == target.instance_index] == REJECTED).all()
    connection.wait(lambda m: is_color_update(m) and m["name"] == "/clutter/frame", mark)
    mine = shown_owner == target.instance_index
    # the first update after the mark may still be the selection's highlight: wait for the newest
    deadline = time.monotonic() + 10
    while not (cloud_colors(connection, mark)[mine] == STATE_RGB[REJECTED]).all():
        assert time.monotonic() < deadline, "the client's colours never showed the decision"
        time.sleep(0.05)
    colors = cloud_colors(connection, mark)
    assert (colors[shown_owner == chosen.instance_index] == SELECTED_RGB).all()


def screen_rect(mode: ClutterMode, camera, points: np.ndarray, pad: float = 0.01):
    """The screen rectangle (corners in 0..1) around the given frame points."""
    screen = ScreenCamera.of(camera)
    px, depth = screen.project(mode.xyz[points])
    uv = px[depth > 0] / np.array([screen.width, screen.height])
    return tuple(uv.min(axis=0) - pad), tuple(uv.max(axis=0) + pad)


def test_panel_width_and_shift_drag_corrections(review: Review) -> None:
    """Large panel (theme and width on the wire, a sharper image), the selection drawn on the
    camera image, a shift-drag that takes part of the selected instance out of it and one that
    adds a missed object: versioned store writes by this user, the colours at once, another
    client following; the default panel back when the mode is left."""
    connection, mode = open_mode(review, "rev")
    watcher, other = open_mode(review, "rev2")
    session = connection.session
    frame_id = mode.frames[mode.frame_index].frame_id
    assert other.frames[other.frame_index].frame_id == frame_id  # both open the same frame

    mark = connection.mark()
    connection.call(mode.set_panel_width, "Large")
    theme = connection.wait(lambda m: m.get("type") == "ThemeConfigurationMessage", mark)
    assert theme["control_width"] == "large"
    width = connection.wait(lambda m: m.get("type") == "GuiSetPanelWidthMessage", mark)
    assert width["width"] >= 700
    assert mode.photo is not None and mode.photo[0].shape[1] == 1280

    # select the instance with the most shown points that project into the camera image
    shown_owner = mode.owner[mode.shown]
    row = mode.pixels[0]
    in_image = np.bincount(
        shown_owner[(shown_owner >= 0) & (row[mode.shown] >= 0)], minlength=len(mode.by_index)
    )
    target = mode.by_index[int(np.argmax(in_image))]
    connection.call(mode.select, target.instance_index)
    image, scale = mode._overlay(), mode.photo[1]
    mine = np.flatnonzero((mode.owner == target.instance_index) & (row >= 0))
    r = np.minimum((row[mine] * scale).astype(int), image.shape[0] - 1)
    c = np.minimum((mode.pixels[1][mine] * scale).astype(int), image.shape[1] - 1)
    assert (image[r, c] == SELECTED_RGB).all(axis=1).mean() > 0.9  # highlighted on the image

    # remove the upper half (on screen) of the instance's shown points from it
    camera = session.client.camera
    points = mode.shown[shown_owner == target.instance_index]
    lo, hi = screen_rect(mode, camera, points)
    hi = (hi[0], 0.5 * (lo[1] + hi[1]))
    inside = rectangle_points(
        mode.xyz[mode.shown], camera, lo, hi, float(mode.point_size.value), RECTANGLE
    )
    taken = mode.shown[inside & (shown_owner == target.instance_index)]
    assert 0 < len(taken) < len(points)
    event = SceneRectSelectEvent(
        client=session.client, client_id=session.client.client_id,
        screen_min=lo, screen_max=hi, modifier="shift",
    )  # fmt: skip
    assert mode.correct_mode.value == REMOVE_FROM_INSTANCE
    mark = connection.mark()
    connection.call(mode.on_rect_select, event)
    with Session(review.engine) as db:
        now = get_instance(db, review.survey_id, target.id)
        corrections = frame_corrections(db, review.survey_id, frame_id)
        audit = db.exec(select(AuditEvent).where(AuditEvent.action == "clutter.remove_points"))
        audit = audit.all()
    assert now.version == target.version + 1 and now.point_count == target.point_count - len(taken)
    assert [c.kind for c in corrections] == ["remove"]
    assert np.array_equal(corrections[0].points, np.sort(taken))
    assert audit[-1].user_id == review.users["rev"][0]
    assert (mode.owner[taken] == -1).all() and not mode.flags[taken].any()  # kept
    colors = None
    deadline = time.monotonic() + 10
    while (
        colors is None
        or (colors[inside & (shown_owner == target.instance_index)] == SELECTED_RGB)
        .all(axis=1)
        .any()
    ):
        assert time.monotonic() < deadline, "the taken points still look selected"
        colors = cloud_colors(connection, mark)
        time.sleep(0.05)
    # the other client follows through the label feed
    deadline = time.monotonic() + 10
    while other.by_index[target.instance_index].version != now.version:
        assert time.monotonic() < deadline, "the other client never saw the correction"
        time.sleep(0.05)
    watcher.call(lambda: None)
    assert (other.owner[taken] == -1).all()

    # add a missed object: free shown points around one near the middle of the screen
    connection.call(lambda: setattr(mode.correct_mode, "value", ADD_OBJECT))
    connection.call(lambda: setattr(mode.object_class, "value", "person"))
    free = mode.shown[mode.owner[mode.shown] < 0]
    screen = ScreenCamera.of(camera)
    px, depth = screen.project(mode.xyz[free])
    uv = px / np.array([screen.width, screen.height])
    ok = (depth > 0) & (uv > 0.2).all(axis=1) & (uv < 0.8).all(axis=1)
    centre = uv[ok][np.argmin(np.abs(uv[ok] - 0.5).sum(axis=1))]
    lo, hi = tuple(centre - 0.03), tuple(centre + 0.03)
    event = SceneRectSelectEvent(
        client=session.client, client_id=session.client.client_id,
        screen_min=lo, screen_max=hi, modifier="shift",
    )  # fmt: skip
    before = len(mode.states)
    connection.call(mode.on_rect_select, event)
    assert len(mode.states) == before + 1
    added = mode.by_index[mode.selected]
    assert added.class_name == "person" and added.decision == Decision.approved
    assert added.version == 1 and added.user_id == review.users["rev"][0]
    assert added.point_count > 0 and (mode.owner == added.instance_index).sum() == added.point_count
    assert (mode.state[mode.owner == added.instance_index] == APPROVED).all()
    assert "person" in mode.rows[-1].label
    deadline = time.monotonic() + 10
    while added.instance_index not in other.by_index:
        assert time.monotonic() < deadline, "the other client never saw the added object"
        time.sleep(0.05)

    # leaving the mode gives the other modes the default panel back
    mark = connection.mark()
    connection.switch("Guardrail review")
    theme = connection.wait(lambda m: m.get("type") == "ThemeConfigurationMessage", mark)
    assert theme["control_width"] == "medium"


def test_a_box_on_the_camera_image_in_3d_corrects_and_adds(review: Review) -> None:
    """ "Through the camera": the image in the scene on its pixels' rays, the view at its optical
    centre. A Ctrl-drag on it is a pixel box (the pointer's ray meets the image): drawn while it
    grows; at release, "Remove from instance" takes the selected instance's points in it out of
    it, "Add missed object" adds the object seen most in it (as `object_in_box` finds it);
    a slip is dropped."""
    connection, mode = open_mode(review, "rev")
    session = connection.session
    mark = connection.mark()
    connection.call(mode.set_view, "Through the camera")
    node = connection.wait(lambda m: m.get("name") == "/clutter/camera_image", mark)
    plane = mode.plane
    wxyz, position, width, height = plane.node_pose()
    assert np.allclose(node["props"]["render_width"], width)
    camera = session.client.camera
    assert np.allclose(camera.position, plane.centre, atol=1e-3)
    # a point the camera sees lands, seen from its centre, on the pixel it has in the image
    seen = np.flatnonzero(mode.projection.in_image)[0]
    screen = ScreenCamera.of(camera)
    size = np.array([screen.width, screen.height], dtype=np.float64)
    px, _ = screen.project(mode.xyz[seen][None].astype(np.float64))
    under = plane.pixel_under(screen, tuple(px[0] / size))
    assert np.allclose(under, mode.projection.uv[seen], atol=0.5)

    def drag_events(a: tuple[float, float], b: tuple[float, float]) -> list[SceneNodeDragEvent]:
        """A Ctrl-drag from pixel a to pixel b on the image, in 6 pointer moves."""
        start = plane.scene_point(*a)
        steps = [
            plane.scene_point(*(np.asarray(a) + k / 6 * (np.subtract(b, a)))) for k in range(7)
        ]
        pos = [tuple((screen.project(p[None])[0][0] / size).tolist()) for p in steps]
        phases = ["start"] + ["update"] * 5 + ["end"]
        return [
            SceneNodeDragEvent(
                client=session.client,
                client_id=session.client.client_id,
                target=mode.image_node,
                phase=phase,
                instance_index=None,
                start_position=tuple(start.tolist()),
                start_screen_pos=pos[0],
                end_position=tuple(steps[k].tolist()),
                end_screen_pos=pos[k],
                button="left",
                modifier="cmd/ctrl",
            )  # fmt: skip
            for k, phase in enumerate(phases)
        ]

    # hover targets: per instance an invisible clickable box round its points in 3D and a
    # quad over its box on the image (the browser outlines them under the pointer); a click on
    # one selects it
    assert mode.targets.boxes and mode.targets.quads
    connection.wait(lambda m: m.get("name") == mode.targets.quads[-1].name, mark)
    boxes = {int(m.name.rsplit("box", 1)[1]): m for m in mode.targets.boxes}
    quads = {int(m.name.rsplit("image", 1)[1]): m for m in mode.targets.quads}
    owners = set(np.unique(mode.owner[mode.owner >= 0]).tolist())
    on_image = set(np.unique(mode.owner[(mode.owner >= 0) & mode.projection.in_image]).tolist())
    assert set(quads) == on_image and set(boxes) <= owners
    for k in owners - set(boxes):  # left out: its box would reach in front of the image
        near = (mode.xyz[mode.owner == k] - plane.centre) @ plane.rotation[:, 2]
        assert near.min() < 1.5 * plane.depth
    k = min(set(boxes) & on_image)
    corners = np.asarray(boxes[k].vertices, dtype=np.float64)
    inside = mode.xyz[mode.owner == k]
    assert (inside >= corners.min(axis=0) - 1e-3).all()
    assert (inside <= corners.max(axis=0) + 1e-3).all()
    quad = np.asarray(quads[k].vertices, dtype=np.float64)  # a slab just in front of the image
    depth = (quad - plane.centre) @ plane.rotation[:, 2]
    assert (depth < plane.depth).all() and all(plane.holds(p) for p in quad)
    uv = mode.projection.uv[(mode.owner == k) & mode.projection.in_image]
    seen = np.array([plane.pixel_of(p) for p in quad])
    assert np.allclose(seen.min(axis=0), uv.min(axis=0), atol=0.5)
    assert np.allclose(seen.max(axis=0), uv.max(axis=0), atol=0.5)
    # front faces outwards: only they catch the pointer
    for mesh in (boxes[k], quads[k]):
        v = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces)
        normal = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
        out = v[faces].mean(axis=1) - v.mean(axis=0)
        assert (np.einsum("ij,ij->i", normal, out) > 0).all()
    connection.call(mode.select_target, k)
    assert mode.selected == k and f"Selected #{k}" in mode.status.content

    # the selected instance's points in the box's upper half leave it
    row, col = mode.pixels
    in_image = np.bincount(mode.owner[(mode.owner >= 0) & (row >= 0)], minlength=1)
    target = mode.by_index[int(np.argmax(in_image))]
    connection.call(mode.select, target.instance_index)
    uv = mode.projection.uv[(mode.owner == target.instance_index) & mode.projection.in_image]
    (u0, v0), (u1, v1) = uv.min(axis=0) - 2, uv.max(axis=0) + 2
    middle = 0.5 * (v0 + v1)
    events = drag_events((u1, v0), (u0, middle))  # drawn from the top right corner
    for event in events[:-1]:
        connection.call(mode.on_box, event)
    assert mode.box_node is not None  # drawn while it grows
    expected = np.flatnonzero(
        (mode.owner == target.instance_index)
        & mode.projection.in_image
        & PixelBox(u0, v0, u1, middle).holds(mode.projection.uv)
    )
    assert 0 < len(expected) < target.point_count
    connection.call(mode.on_box, events[-1])
    assert mode.box_node is None
    with Session(review.engine) as db:
        now = get_instance(db, review.survey_id, target.id)
    assert now.point_count == target.point_count - len(expected)
    assert (mode.owner[expected] == -1).all()

    # add: a box round free points above the ground gives the object object_in_box finds
    connection.call(lambda: setattr(mode.correct_mode, "value", ADD_OBJECT))
    connection.call(lambda: setattr(mode.object_class, "value", "bicycle"))
    free = np.flatnonzero((mode.owner < 0) & mode.projection.in_image)
    for k in free[np.argsort(mode.projection.depth[free])]:
        centre = mode.projection.uv[k]
        box = PixelBox(*(centre - 25), *(centre + 25)).clipped(plane.width, plane.height)
        wanted = object_in_box(mode.sensor_xyz, mode.projection, mode.owner, box, mode.run_config)
        if len(wanted) >= 20:
            break
    else:
        pytest.fail("no free object above the ground in the simulated frame's image")
    before = len(mode.states)
    for event in drag_events((box.u0, box.v0), (box.u1, box.v1)):
        connection.call(mode.on_box, event)
    assert len(mode.states) == before + 1
    added = mode.by_index[mode.selected]
    assert added.class_name == "bicycle" and added.decision == Decision.approved
    assert set(np.flatnonzero(mode.owner == added.instance_index)) == set(wanted)
    assert added.bbox == box.as_bbox()
    # a slip (a box a pixel wide) is dropped
    for event in drag_events((100.0, 100.0), (101.0, 160.0)):
        connection.call(mode.on_box, event)
    assert "Box dropped" in mode.status.content and len(mode.states) == before + 1
    # behind the car again: the image leaves the scene with the view's own field of view
    connection.call(mode.set_view, "Behind the car")
    assert mode.image_node is None and camera.fov == pytest.approx(mode.view_fov)
