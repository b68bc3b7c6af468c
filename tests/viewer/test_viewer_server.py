"""The viewer behind the login, on a real `mmsclean serve` with the sample survey: nothing of it
without a login, viser on loopback only, and a logged-in websocket client gets the scene,
labels with the brush as its own user, sees API writes recoloured and can undo."""

from __future__ import annotations

import asyncio
import ipaddress
import socket
import subprocess
import time
from pathlib import Path
from urllib.parse import unquote

import httpx
import numpy as np
import pytest
from sqlmodel import Session
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from app.core.sensors import SensorKind
from app.io import open_survey
from app.store.db import make_engine
from app.store.model_labels import store_model_labels
from app.store.model_versions import register_version
from app.store.models import Pipeline
from app.store.pillar_labels import STORE_GRID
from app.viewer.pillar_colors import PALETTE, pillar_colors
from tests.api.server import Server
from tests.viewer.conftest import OVERVIEW_POINTS, TILE_POINTS, login_token
from tests.viewer.wire import (
    SUBPROTOCOL,
    WireClient,
    button_press,
    click_message,
    gui_set,
    is_color_update,
    is_point_cloud,
    run_coroutine,
)

SCENE_TIMEOUT = 120.0  # the first open builds the sample's map (seconds on 2 shared cores)


def ws_url(server: Server, query: str = "") -> str:
    return f"ws://127.0.0.1:{server.port}/viewer/ws{query}"


def viser_port(server: Server) -> int:
    return int(server.env["MMSCLEAN_VIEWER_PORT"])


def refused_status(url: str, **kwargs) -> int:
    """The HTTP status a refused websocket handshake got."""

    async def attempt() -> int:
        try:
            async with connect(url, subprotocols=[SUBPROTOCOL], **kwargs):
                return 101
        except InvalidStatus as exc:
            return exc.response.status_code

    return run_coroutine(attempt())


# --- nothing without a login -----------------------------------------------------------------


def test_relay_refuses_without_a_valid_token(viewer_server: Server) -> None:
    assert refused_status(ws_url(viewer_server)) == 403
    assert refused_status(ws_url(viewer_server, "?token=not-a-token")) == 403
    forged = {"Cookie": "mmsclean_token=eyJhbGciOi.forged.token"}
    assert refused_status(ws_url(viewer_server), additional_headers=forged) == 403


def test_relay_refuses_other_origins_unknown_surveys_and_other_protocols(
    viewer_server: Server,
) -> None:
    token = login_token(viewer_server)
    cookie = {"Cookie": f"mmsclean_token={token}"}
    evil = {**cookie, "Origin": "http://127.0.0.1:1"}  # another port is another origin
    assert refused_status(ws_url(viewer_server), additional_headers=evil) == 403
    assert refused_status(ws_url(viewer_server, "?survey=999"), additional_headers=cookie) == 403

    async def no_viser_protocol() -> int:
        try:
            async with connect(ws_url(viewer_server), additional_headers=cookie):
                return 101
        except InvalidStatus as exc:
            return exc.response.status_code

    assert run_coroutine(no_viser_protocol()) == 403


def test_viewer_page_needs_a_login(viewer_server: Server) -> None:
    browser = httpx.get(f"{viewer_server.url}/viewer?survey=1", headers={"Accept": "text/html"})
    assert browser.status_code == 303
    assert browser.headers["location"] == "/?next=%2Fviewer%3Fsurvey%3D1"
    assert "Viser" not in browser.text
    script = httpx.get(f"{viewer_server.url}/viewer")
    assert script.status_code == 401 and "not logged in" in script.json()["detail"]


def test_viewer_page_points_viser_at_the_relay(viewer_server: Server) -> None:
    token = login_token(viewer_server)
    with httpx.Client(base_url=viewer_server.url, cookies={"mmsclean_token": token}) as client:
        first = client.get("/viewer", params={"survey": 1})
        assert first.status_code == 303
        location = first.headers["location"]
        relay = f"ws://127.0.0.1:{viewer_server.port}/viewer/ws?survey=1"
        assert unquote(location) == f"/viewer?websocket={relay}"
        page = client.get(location)
        assert page.status_code == 200 and "<title>Viser</title>" in page.text
        # the address bar form viser writes back (unescaped) is served as is
        assert client.get(f"/viewer?websocket={relay}").status_code == 200
        # a page pointed anywhere else is sent back to our relay
        elsewhere = client.get("/viewer", params={"websocket": "ws://evil.example/ws"})
        assert elsewhere.status_code == 303 and "evil" not in elsewhere.headers["location"]
        assert client.get("/viewer", params={"survey": 999}).status_code == 404
        # the dashboard's mode links ride along to the relay, which hands them to the session
        moded = client.get("/viewer", params={"survey": 1, "mode": "qa"})
        assert unquote(moded.headers["location"]).endswith("/viewer/ws?survey=1&mode=qa")
        assert client.get(moded.headers["location"]).status_code == 200
        unknown = client.get("/viewer", params={"survey": 1, "mode": "paint"})
        assert unknown.status_code == 422 and unknown.json()["detail"].startswith("mode:")
        # a person who followed a link reads a page, not the API's JSON (issue 20)
        html = {"Accept": "text/html"}
        missing = client.get("/viewer", params={"survey": 999}, headers=html)
        assert missing.status_code == 404
        assert missing.headers["content-type"].startswith("text/html")
        assert "Survey 999 does not exist." in missing.text and 'href="/#/surveys"' in missing.text
        painted = client.get("/viewer", params={"survey": 1, "mode": "paint"}, headers=html)
        assert painted.status_code == 422
        assert "unknown viewer mode &#x27;paint&#x27;" in painted.text


# --- viser listens on loopback only ----------------------------------------------------------


def other_addresses() -> list[str]:
    """This machine's addresses that are not loopback."""
    found: set[str] = set()
    try:
        out = subprocess.run(["hostname", "-I"], capture_output=True, text=True, timeout=5)
        found.update(out.stdout.split())
    except (OSError, subprocess.SubprocessError):
        pass
    try:  # the address of the default route (no packet is sent)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))
            found.add(probe.getsockname()[0])
    except OSError:
        pass
    return sorted(a for a in found if not ipaddress.ip_address(a.split("%")[0]).is_loopback)


def answers(address: str, port: int) -> bool:
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.settimeout(2)
        try:
            probe.connect((address, port))
            return True
        except OSError:
            return False


def test_viser_answers_on_loopback_only(viewer_server: Server) -> None:
    port = viser_port(viewer_server)
    assert answers("127.0.0.1", port)
    addresses = other_addresses()
    if not addresses:
        pytest.skip("this machine has no address other than loopback")
    reachable = [a for a in addresses if answers(a, port)]
    assert not reachable, f"viser answers on {reachable}"


def test_direct_connection_to_viser_is_closed_before_any_frame(viewer_server: Server) -> None:
    """Any local process dialling viser's loopback port with viser's own subprotocol but no
    ticket (a guessed nonce, or none) is closed at once with 1008 and receives no frame."""

    async def dial(path: str) -> tuple[int | None, str]:
        url = f"ws://127.0.0.1:{viser_port(viewer_server)}{path}"
        async with connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as ws:
            try:
                frame = await asyncio.wait_for(ws.recv(), 10)
            except ConnectionClosed:
                return ws.close_code, "no frame"
            except TimeoutError:
                return ws.close_code, "stayed open"
            return ws.close_code, f"a frame of {len(frame)} bytes"

    for path in ("/", "/?session=guessed"):
        assert run_coroutine(dial(path)) == (1008, "no frame")


# --- a logged-in client ----------------------------------------------------------------------


def human_labels(api: httpx.Client, box: tuple[float, float, float, float]) -> dict:
    x0, y0, x1, y1 = box
    tile = api.get(
        "/surveys/1/pillars/labels",
        params={"x0": x0, "y0": y0, "x1": x1, "y1": y1, "source": "human"},
    ).json()
    rows = zip(tile["cell_id"], tile["label"], tile["user_id"], strict=True)
    return {cell: (label, user) for cell, label, user in rows}


def colors_with(rgb: np.ndarray, present: bool = True):
    """Predicate: a colour update that does (or does not) hold this colour."""

    def predicate(message: dict) -> bool:
        if not is_color_update(message):
            return False
        colors = np.asarray(message["updates"]["colors"]).reshape(-1, 3)
        return bool((colors == rgb).all(axis=1).any()) == present

    return predicate


def test_client_gets_the_scene_labels_as_its_user_sees_api_writes_and_undoes(
    viewer_server: Server,
) -> None:
    painter = viewer_server.add_user("painter", "annotator")
    painter_id = painter.get("/auth/me").json()["id"]
    token = login_token(viewer_server, "painter", "password-123")
    admin = viewer_server.client()
    survey = admin.get("/surveys/1").json()
    origin = np.array(survey["origin"])

    async def session() -> None:
        client = await WireClient.open(ws_url(viewer_server, "?survey=1"), token)
        await client.hello()
        _, overview = await client.wait_for(is_point_cloud, SCENE_TIMEOUT)
        assert overview["name"] == "/pillars/overview"
        points = overview["props"]["points"]
        assert points.dtype == np.float32 and overview["props"]["precision"] == "float32"
        assert 0 < len(points) // 3 <= OVERVIEW_POINTS
        assert len(overview["props"]["colors"]) == len(points)  # one RGB per point
        _, tile = await client.wait_for(is_point_cloud, 30)
        assert tile["name"] == "/pillars/tile" and len(tile["props"]["points"]) // 3 <= TILE_POINTS
        # the first camera looks at a point of the map (a long drive's middle may hold none)
        look = next(m for _, m in client.received if m.get("type") == "SetCameraLookAtMessage")
        shown = np.asarray(points).reshape(-1, 3)[:, :2]
        assert np.hypot(*(shown - np.asarray(look["look_at"][:2])).T).min() < 0.01

        # brush: a click straight down at local (30, 0) paints the pillars within 1 m of the
        # surface point under the cursor (a shown point a few centimetres from the ray)
        await client.send(click_message((30.0, 0.0, 40.0), (0.0, 0.0, -1.0)))
        await client.wait_for(colors_with(PALETTE[0]), 30)  # ground, full colour
        world = origin[:2] + np.array([30.0, 0.0])
        box = (world[0] - 2, world[1] - 2, world[0] + 2, world[1] + 2)
        # the colours go out before the store's write (`ViewerSession.write_pillar_labels`)
        deadline = time.monotonic() + 10.0
        while not (painted := human_labels(admin, box)) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        assert 50 <= len(painted) <= 85  # pi * 1 m^2 / 0.04 m^2 ~ 79 pillars, those with points
        assert {v for v in painted.values()} == {(0, painter_id)}  # ground, by the painter
        centres = STORE_GRID.cell_center(*STORE_GRID.decode(np.array(list(painted))))
        assert np.hypot(*(centres - world).T).max() <= 1.2

        # a write through the REST API by someone else shows up in this client's colours
        cells = STORE_GRID.point_cell_ids(world + np.array([[5.0, 0.0], [5.2, 0.0]]))
        started = time.perf_counter()
        written = admin.put(
            "/surveys/1/pillars/labels",
            json={"labels": [{"cell_id": int(c), "label": 3} for c in cells]},
        )
        assert written.status_code == 200
        arrived, _ = await client.wait_for(colors_with(PALETTE[3]), 10)  # phantom
        assert arrived - started < 5.0

        # undo (the GUI button) takes the painter's brush stroke back, not the admin's labels
        await client.send(button_press(client.gui_uuid("Undo (Ctrl+Z)")))
        await client.wait_for(colors_with(PALETTE[0], present=False), 30)
        assert human_labels(admin, box) == {}
        beside = (world[0] + 4, world[1] - 1, world[0] + 6, world[1] + 1)
        assert len(human_labels(admin, beside)) == 2
        await client.close()

    run_coroutine(session())


def test_model_prelabels_from_another_process_show_lighter_hide_and_lead_the_camera(
    viewer_server: Server,
) -> None:
    """A job process replaces the model pre-labels: open clients recolour them (lighter), hiding
    their class drops their points, "Next uncertain area" flies the camera to them (and before
    any pre-label says there are none yet, not that every doubtful one is reviewed)."""
    token = login_token(viewer_server)
    origin = np.array(viewer_server.client().get("/surveys/1").json()["origin"])
    engine = make_engine(f"sqlite:///{viewer_server.data_dir / 'mmsclean.sqlite3'}")

    async def session() -> None:
        client = await WireClient.open(ws_url(viewer_server, "?survey=1"), token)
        await client.hello()
        _, overview = await client.wait_for(is_point_cloud, SCENE_TIMEOUT)
        local = np.asarray(overview["props"]["points"]).reshape(-1, 3)
        spot = np.array([12.0, 4.0])  # local xy: a 3 m patch of unsure phantom pre-labels
        near = np.hypot(*(local[:, :2] - spot).T) < 3.0
        cells = np.unique(STORE_GRID.point_cell_ids(local[near, :2] + origin[:2]))
        await client.send(button_press(client.gui_uuid("Next uncertain area (N)")))
        await client.wait_for(lambda m: "No model pre-labels yet" in str(m), 10)
        with Session(engine) as db:
            version = register_version(
                db, Pipeline.phantom, "test", viewer_server.data_dir / "m.pt", {}, {}, None, False,
                SensorKind.PROFILE,
            )  # fmt: skip
            db.commit()
            version_id = version.id
        store_model_labels(
            engine, 1, cells, np.full(len(cells), 3), np.full(len(cells), 0.3), version_id, None, 0
        )
        light = pillar_colors(np.array([-1]), np.array([3]), np.array([0.3]))[0]
        assert (light > PALETTE[3]).all()  # paler than a human phantom label
        await client.wait_for(colors_with(light), 10)

        shown = len(local)
        await client.send(gui_set(client.gui_uuid("Hide phantom", "GuiCheckboxMessage"), True))
        _, redrawn = await client.wait_for(
            lambda m: is_point_cloud(m) and m["name"] == "/pillars/overview", 10
        )
        in_patch = np.isin(STORE_GRID.point_cell_ids(local[:, :2] + origin[:2]), cells)
        # (a point within float32 rounding of a pillar border may be counted in the other one)
        assert abs(len(redrawn["props"]["points"]) // 3 - (shown - int(in_patch.sum()))) <= 2

        await client.send(button_press(client.gui_uuid("Next uncertain area (N)")))
        _, look = await client.wait_for(lambda m: m.get("type") == "SetCameraLookAtMessage", 10)
        target = np.array(look["look_at"][:2])
        grid = (target + origin[:2]) / 10.0 - 0.5  # the centre of a 10 m area ...
        np.testing.assert_allclose(grid, np.round(grid), atol=1e-3)
        assert np.hypot(*(target - spot)) < 5.0 * np.sqrt(2) + 3.0  # ... holding the patch
        await client.close()

    try:
        run_coroutine(session())
    finally:
        engine.dispose()


def test_the_drive_controls_take_the_camera_along_the_drive(viewer_server: Server) -> None:
    """ "Ahead 100 m" on the 58 m sample drive looks at its end; the slider at 20 m looks at
    the drive 20 m from its start, from behind it (`app/viewer/drive.py`)."""
    token = login_token(viewer_server)
    origin = np.array(viewer_server.client().get("/surveys/1").json()["origin"])
    sample = Path(__file__).resolve().parents[2] / "data_samples" / "urban-60m"
    path = open_survey(sample, "sim").poses()[:, :3, 3] - origin

    def looked_at(message: dict) -> bool:
        return message.get("type") == "SetCameraLookAtMessage"

    async def session() -> None:
        client = await WireClient.open(ws_url(viewer_server, "?survey=1"), token)
        await client.hello()
        await client.wait_for(is_point_cloud, SCENE_TIMEOUT)  # past the first camera
        await client.send(button_press(client.gui_uuid("Ahead 100 m")))
        _, look = await client.wait_for(looked_at, 10)
        assert np.hypot(*(np.asarray(look["look_at"][:2]) - path[-1, :2])) < 0.01
        slider = client.gui_uuid("Along the drive (m)", "GuiSliderMessage")
        await client.send(gui_set(slider, 20.0))
        _, look = await client.wait_for(looked_at, 10)
        step = np.hypot(*np.diff(path[:, :2], axis=0).T)
        at = np.asarray(look["look_at"][:2])
        assert np.hypot(*(path[:, :2] - at).T).min() < 0.5  # on the drive
        along = np.interp(20.0, np.r_[0, np.cumsum(step)], np.arange(len(path)))
        assert np.hypot(*(at - path[int(round(along)), :2])) < max(step) + 0.5
        await client.close()

    run_coroutine(session())


def test_a_work_area_link_opens_the_viewer_looking_at_the_area(viewer_server: Server) -> None:
    """The work areas table's viewer link (`/viewer?survey=1&mode=pillars&area=ID`) rides to
    the relay and the session looks down at the area's box; an area of no survey, or without
    a survey, is refused with the field named (issue 20: areas assigned to annotators)."""
    token = login_token(viewer_server)
    admin = viewer_server.client()
    cut = admin.post("/surveys/1/areas", json={"length_m": 20.0, "replace": True})
    assert cut.status_code == 201, cut.text
    area = cut.json()[-1]  # the last of three: far from the middle the survey opens at
    origin = np.array(admin.get("/surveys/1").json()["origin"])
    centre = np.array([area["x_min"] + area["x_max"], area["y_min"] + area["y_max"]]) / 2.0
    with httpx.Client(base_url=viewer_server.url, cookies={"mmsclean_token": token}) as client:
        params = {"survey": 1, "mode": "pillars", "area": area["id"]}
        first = client.get("/viewer", params=params)
        assert first.status_code == 303
        assert unquote(first.headers["location"]).endswith(
            f"/viewer/ws?survey=1&mode=pillars&area={area['id']}"
        )
        assert client.get(first.headers["location"]).status_code == 200
        missing = client.get("/viewer", params={"survey": 1, "area": 99_999})
        assert missing.status_code == 404 and "work area 99999" in missing.json()["detail"]
        page = client.get(
            "/viewer", params={"survey": 1, "area": 99_999}, headers={"Accept": "text/html"}
        )
        assert page.status_code == 404 and "Survey 1 has no work area 99999." in page.text
        alone = client.get("/viewer", params={"area": area["id"]})
        assert alone.status_code == 422 and alone.json()["detail"].startswith("area:")

    def looked_at(message: dict) -> bool:
        return message.get("type") == "SetCameraLookAtMessage"

    async def session() -> None:
        query = f"?survey=1&mode=pillars&area={area['id']}"
        client = await WireClient.open(ws_url(viewer_server, query), token)
        await client.hello()
        await client.wait_for(is_point_cloud, SCENE_TIMEOUT)
        looks = [m for _, m in client.received if looked_at(m)]
        assert looks, "the camera was never placed"
        at = np.asarray(looks[-1]["look_at"][:2], dtype=np.float64)
        assert np.hypot(*(at - (centre - origin[:2]))) < 0.01
        await client.close()

    run_coroutine(session())
