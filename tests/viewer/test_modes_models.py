"""Model inspection mode on a real `run:guardrail` (a simulated street with a pipe and a beam
guardrail): one mesh per model at its place over its slice points, the list with kind / units /
ICP residual / status, accept / reject by reviewers with versions (stale: reloaded), the export
link, read-only for annotators."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest
import trimesh
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.core.errors import PermissionDeniedError
from app.store.audit import audit
from app.store.guardrail_review import decide_model, get_model, list_models
from app.store.models import ModelStatus, User
from app.viewer.modes.models import SELECTED_RGB, STATUS_RGB, ModelMode, load_mesh
from tests.viewer.test_modes_common import SCENE_POINTS, Connection, Driver
from tests.viewer.test_modes_guardrails import guardrail_street
from tests.viewer.wire import is_point_cloud


@dataclass
class Street:
    driver: Driver
    engine: Engine
    survey_id: int
    users: dict[str, tuple[int, str]]


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Street]:
    driver, engine, survey_id, users = guardrail_street(tmp_path_factory.mktemp("model-mode"))
    yield Street(driver, engine, survey_id, users)
    driver.close()
    engine.dispose()


def open_mode(street: Street, user: str) -> tuple[Connection, ModelMode]:
    connection = street.driver.connect(*street.users[user], street.survey_id)
    return connection, connection.switch("Model inspection")


def test_meshes_sit_over_their_points_and_the_list_describes_them(street: Street) -> None:
    connection, mode = open_mode(street, "rev")
    with Session(street.engine) as session:
        models = list_models(session, street.survey_id)
    assert sorted(m.kind.value for m in models) == ["beam", "pipe"]
    cloud = connection.wait(lambda m: is_point_cloud(m) and m["name"] == "/models/points")
    for m in models:  # the meshes follow the points
        connection.wait(lambda x, n=f"/models/mesh/{m.id}": x.get("name") == n)
    meshes = {
        m["name"]: m
        for m in connection.since(0, lambda m: m.get("type") == "MeshMessage")
        if m["name"].startswith("/models/mesh/")  # not the selected one's outline
    }
    assert set(meshes) == {f"/models/mesh/{m.id}" for m in models}
    assert 0 < len(np.asarray(cloud["props"]["points"])) // 3 <= SCENE_POINTS
    for m in models:
        message = meshes[f"/models/mesh/{m.id}"]
        vertices = np.asarray(message["props"]["vertices"]).reshape(-1, 3)
        assert vertices.dtype == np.float32
        position = np.asarray(message["props"].get("position", (0, 0, 0)), dtype=np.float64)
        if "position" not in message["props"]:  # sent as a separate transform message
            position = np.asarray(
                connection.wait(
                    lambda x, n=message["name"]: (
                        x.get("type") == "SetPositionMessage" and x.get("name") == n
                    )
                )["position"]
            )
        # the mesh lies where the exported world mesh lies (re-centred on the survey origin)
        world = trimesh.load(m.params["files"]["obj"], force="mesh").vertices
        lo = vertices.min(axis=0) + position
        np.testing.assert_allclose(lo, world.min(axis=0) - mode.origin, atol=2e-3)
        # ... over its own slice points
        mine = mode.xyz[mode.point_model == m.id]
        assert len(mine)
        centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2 + position
        assert np.linalg.norm(mine.mean(axis=0)[:2] - centre[:2]) < 5.0
    table = mode.table.content
    for m in models:
        residual = f"{m.icp_residual:.3f} m" if m.icp_residual is not None else "n/a"
        assert f"| {m.kind.value} | {m.unit_count} | {residual} | pending |" in table
    assert f"/surveys/{street.survey_id}/exports/guardrails.zip" in "".join(
        str(m.get("props", {}).get("_markdown", "")) for m in connection.since(0, lambda m: True)
    )


def test_load_mesh_keeps_the_local_frame(street: Street) -> None:
    with Session(street.engine) as session:
        model = list_models(session, street.survey_id)[0]
    vertices, faces, origin = load_mesh(model.mesh_path)
    # as written: trimesh would otherwise merge the OBJ's duplicate vertices, which the glTF keeps
    world = trimesh.load(model.params["files"]["obj"], force="mesh", process=False)
    np.testing.assert_allclose(origin, model.params["origin"], atol=1e-9)
    np.testing.assert_allclose(vertices + origin, world.vertices, atol=1e-3)
    assert len(faces) == len(world.faces)


def test_reviewers_accept_and_reject_with_versions(street: Street) -> None:
    connection, mode = open_mode(street, "rev")
    first, second = mode.models[0], mode.models[1]
    connection.call(mode.select, first.id)
    # selected: outlined in orange over its own review colour (issue 20: the selection colour
    # hid the decision, a rejected model still looked selected)
    assert mode.meshes[first.id].color == STATUS_RGB[first.status]
    assert mode.outline.name == f"/models/selected/{first.id}"
    assert mode.outline.color == SELECTED_RGB and mode.outline.wireframe
    connection.call(mode.decide, first.id, ModelStatus.approved)
    assert mode.meshes[first.id].color == STATUS_RGB[ModelStatus.approved]
    connection.call(mode.decide, second.id, ModelStatus.rejected)
    with Session(street.engine) as session:
        a, b = (
            get_model(session, street.survey_id, first.id),
            get_model(session, street.survey_id, second.id),
        )
    assert (a.status, a.version, a.decided_by) == (
        ModelStatus.approved,
        first.version + 1,
        street.users["rev"][0],
    )
    assert (b.status, b.version) == (ModelStatus.rejected, second.version + 1)
    assert mode.meshes[second.id].color == STATUS_RGB[ModelStatus.rejected]
    assert "| approved |" in mode.table.content and "| rejected |" in mode.table.content

    # another reviewer changes the first one meanwhile: a write at the version we held is
    # refused and the list reloads (the live feed may have reloaded it already)
    held = mode._model(first.id)
    with Session(street.engine) as session:
        rev2 = session.get(User, street.users["rev2"][0])
        decide_model(session, street.survey_id, a.id, a.version, ModelStatus.rejected, rev2)

    def stale_decide() -> None:  # on the session's thread: no live reload in between
        mode.models = [held if m.id == held.id else m for m in mode.models]  # as if not seen
        mode.decide(held.id, ModelStatus.approved)  # holds version a.version

    stale_mode = connection.mark()
    connection.call(stale_decide)
    connection.wait(lambda m: m.get("type") == "NotificationShowMessage", stale_mode)
    with Session(street.engine) as session:
        now = get_model(session, street.survey_id, first.id)
    assert now.status == ModelStatus.rejected and now.decided_by == street.users["rev2"][0]
    assert mode._model(first.id).version == now.version


def test_annotators_cannot_decide(street: Street) -> None:
    connection, mode = open_mode(street, "ann")
    assert not mode.decision.visible and "Read only" in mode.status.content
    model = mode.models[0]
    with pytest.raises(PermissionDeniedError):
        connection.call(mode.decide, model.id, ModelStatus.approved)
    with Session(street.engine) as session:
        assert get_model(session, street.survey_id, model.id).version == model.version


def test_decisions_by_someone_else_show_up_live(street: Street) -> None:
    """Another reviewer decides a model straight through the store: the list and the mesh's
    colour follow within seconds, the selection stays; a rebuild reloads the meshes."""
    connection, mode = open_mode(street, "rev")
    chosen, target = mode.models[0], mode.models[1]
    connection.call(mode.select, chosen.id)
    new = ModelStatus.approved if target.status != ModelStatus.approved else ModelStatus.rejected
    mark = connection.mark()
    with Session(street.engine) as session:
        rev2 = session.get(User, street.users["rev2"][0])
        decide_model(session, street.survey_id, target.id, target.version, new, rev2)
    deadline = time.monotonic() + 10
    while mode._model(target.id).status != new:
        assert time.monotonic() < deadline, "the list never saw the other decision"
        time.sleep(0.05)
    connection.call(lambda: None)  # the recolouring has finished
    assert mode._model(target.id).version == target.version + 1
    assert mode.selected == chosen.id and mode.meshes[target.id].color == STATUS_RGB[new]
    assert f"| {new.value} |" in mode.table.content
    connection.wait(
        lambda m: (
            m.get("type") == "SceneNodeUpdateMessage"
            and m.get("name") == f"/models/mesh/{target.id}"
            and tuple(m["updates"].get("color", ())) == STATUS_RGB[new]
        ),
        mark,
    )

    # a rebuild (its audit event) reloads the mode: fresh meshes, the selection kept
    mark = connection.mark()
    with Session(street.engine) as session:
        audit(session, None, "guardrail.rebuild", "survey", street.survey_id)
        session.commit()
    fresh = connection.reloaded(mode)
    assert isinstance(fresh, ModelMode) and fresh.selected == chosen.id
    assert fresh._model(target.id).status == new
    connection.wait(lambda m: m.get("name") == f"/models/mesh/{target.id}", mark)
