"""The review modes' shared pieces (picking along a click ray, decisions applied to points) and
the harness the mode tests drive them with: an in-process `ViewerServer` on a free loopback port
and a viser wire client (`tests.viewer.wire`) connected with a ticket, as the relay would do,
reading every message in the background. Mode methods run on the session's own worker thread
(`Connection.call`), as viser's callbacks would run them; what reaches the client is checked on
the wire."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy.engine import Engine
from sqlmodel import Session
from viser import SceneClickEvent

from app.core.settings import Settings
from app.io import open_survey
from app.io.ply import write_ply
from app.store.db import init_db, make_engine
from app.store.models import Decision, Role
from app.store.surveys import register_opened_survey
from app.store.users import create_user
from app.viewer.modes import MODES
from app.viewer.modes.clutter_states import (
    APPROVED,
    KEPT,
    KEPT_PENDING,
    REJECTED,
    REMOVED_PENDING,
    point_states,
)
from app.viewer.modes.common import evenly
from app.viewer.server import ViewerServer
from app.viewer.session import ViewerSession
from tests.viewer.wire import WireClient, decode_frame

SCENE_POINTS = 20_000  # browser scenes stay small in the tests
OPEN_TIMEOUT = 180.0  # the first open builds the survey's map (seconds on 2 shared cores)


# --- harness ---------------------------------------------------------------------------------


class Connection:
    """One wire client and the server-side session it got."""

    def __init__(self, client: WireClient, session: ViewerSession, loop: asyncio.AbstractEventLoop):
        self.client = client
        self.session = session
        self.loop = loop
        self.messages: list[dict[str, Any]] = []
        self.lock = threading.Lock()

    @property
    def mode(self) -> Any:
        return self.session.mode

    def call(self, fn: Callable[..., Any], *args: Any, timeout: float = 120.0) -> Any:
        """fn(*args) on the session's worker thread; exceptions come back here (unlike the
        session's own guard, which turns them into notifications)."""

        def boxed() -> tuple[bool, Any]:
            try:
                return True, fn(*args)
            except BaseException as exc:  # re-raised in the test thread
                return False, exc

        future = self.session.submit(boxed)
        assert future is not None, "the session is closed"
        ok, value = future.result(timeout)
        if not ok:
            raise value
        return value

    def switch(self, mode_name: str) -> Any:
        self.call(self.session.switch_mode, mode_name)
        assert self.mode is not None and self.mode.name == mode_name
        return self.mode

    def reloaded(self, mode: Any, timeout: float = 30.0) -> Any:
        """The fresh mode the session entered in place of `mode` (a live reload), once its
        entering is done."""
        deadline = time.monotonic() + timeout
        while self.mode is mode:
            assert time.monotonic() < deadline, "the mode was not reloaded"
            time.sleep(0.05)
        self.call(lambda: None)
        return self.mode

    def mark(self) -> int:
        with self.lock:
            return len(self.messages)

    def since(self, mark: int, predicate: Callable[[dict[str, Any]], bool]) -> list[dict]:
        with self.lock:
            return [m for m in self.messages[mark:] if predicate(m)]

    def wait(
        self, predicate: Callable[[dict[str, Any]], bool], since: int = 0, timeout: float = 30.0
    ) -> dict[str, Any]:
        """The first message after `since` matching `predicate` (waiting for it)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = self.since(since, predicate)
            if found:
                return found[0]
            time.sleep(0.05)
        raise TimeoutError("no matching viser message in time")

    def send(self, frame: bytes) -> None:
        asyncio.run_coroutine_threadsafe(self.client.send(frame), self.loop).result(10)


class Driver:
    """An in-process viewer and an event loop (in a thread) for its wire clients."""

    def __init__(self, settings: Settings, engine: Engine):
        self.viewer = ViewerServer(settings, engine).start()
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.connections: list[Connection] = []

    def connect(self, user_id: int, username: str, survey_id: int) -> Connection:
        """A client as the relay would connect it (ticket in the upstream path), once its
        session has opened the survey."""
        nonce = self.viewer.issue_ticket(user_id, username, survey_id)
        before = set(self.viewer.sessions)
        url = f"ws://127.0.0.1:{self.viewer.port}/?session={nonce}"

        async def open_client() -> WireClient:
            client = await WireClient.open(url)
            await client.hello()
            return client

        client = asyncio.run_coroutine_threadsafe(open_client(), self.loop).result(30)
        deadline = time.monotonic() + OPEN_TIMEOUT
        session = None
        while time.monotonic() < deadline:
            new = set(self.viewer.sessions) - before
            if new:
                session = self.viewer.sessions[new.pop()]
                break
            time.sleep(0.05)
        assert session is not None, "the viewer made no session for the client"
        connection = Connection(client, session, self.loop)
        asyncio.run_coroutine_threadsafe(self._read(connection), self.loop)
        while time.monotonic() < deadline and session.mode is None:
            time.sleep(0.1)
        assert session.mode is not None, "the session did not open the survey in time"
        self.connections.append(connection)
        return connection

    async def _read(self, connection: Connection) -> None:
        try:
            async for frame in connection.client.connection:
                messages = decode_frame(frame)
                with connection.lock:
                    connection.messages += messages
        except Exception:  # closed: the test is over
            return

    def close(self) -> None:
        for connection in self.connections:
            asyncio.run_coroutine_threadsafe(connection.client.close(), self.loop).result(10)
        self.viewer.stop()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


def viewer_settings(root: Path, **extra: Any) -> Settings:
    return Settings(
        data_dir=root / "var",
        sample_dir=None,
        viewer_overview_points=SCENE_POINTS,
        viewer_tile_points=SCENE_POINTS,
        **extra,
    )


def new_engine(settings: Settings) -> Engine:
    engine = make_engine(settings.database_url)
    init_db(engine)
    return engine


def add_users(engine: Engine) -> dict[str, tuple[int, str]]:
    """An annotator and a reviewer (and a second reviewer): name -> (id, name)."""
    users = {}
    with Session(engine) as session:
        for name, role in (
            ("ann", Role.annotator),
            ("rev", Role.reviewer),
            ("rev2", Role.reviewer),
        ):
            users[name] = (create_user(session, name, "password-123", role).id, name)
    return users


# --- shared pieces -------------------------------------------------------------------------


def test_modes_are_registered_once_each() -> None:
    names = [m.name for m in MODES]
    assert names[0] == "Pillar labelling"
    assert {"Clutter review", "Guardrail review", "Model inspection", "QA"} <= set(names)
    assert len(set(names)) == len(names) and len({m.key for m in MODES}) == len(MODES)


def test_evenly_keeps_a_fixed_spread_subset() -> None:
    values = np.arange(100, 200)
    assert np.array_equal(evenly(values, 500), values)
    picked = evenly(values, 10)
    assert len(picked) == 10 and picked[0] == 100 and picked[-1] == 199
    assert np.array_equal(picked, evenly(values, 10))


def test_point_states_apply_decisions_as_the_recompute_does() -> None:
    # points: no instance (kept, removed by free space alone), instance 0 (two removed, one
    # kept by the pipeline), instance 1 (removed), instance 2 (one removed, one kept)
    owner = np.array([-1, -1, 0, 0, 0, 1, 2, 2])
    flags = np.array([0, 1, 1, 1, 0, 1, 1, 0], dtype=bool)
    pending = point_states(owner, flags, np.array([0, 1, 2]), [Decision.pending] * 3)
    assert pending.tolist() == [
        KEPT, REMOVED_PENDING, REMOVED_PENDING, REMOVED_PENDING, KEPT_PENDING, REMOVED_PENDING,
        REMOVED_PENDING, KEPT_PENDING,
    ]  # fmt: skip
    decided = point_states(
        owner,
        flags,
        np.array([0, 1, 2]),
        [Decision.approved, Decision.rejected, Decision.pending],
    )
    assert decided.tolist() == [
        KEPT, REMOVED_PENDING, APPROVED, APPROVED, APPROVED, REJECTED, REMOVED_PENDING,
        KEPT_PENDING,
    ]  # fmt: skip
    # an instance the store does not list keeps the pipeline's flags
    partial = point_states(owner, flags, np.array([1]), [Decision.approved])
    assert partial[2:5].tolist() == [REMOVED_PENDING, REMOVED_PENDING, KEPT_PENDING]
    assert partial[5] == APPROVED


def test_modes_without_a_pipeline_run_say_so(tmp_path: Path) -> None:
    """On a survey no pipeline ran on, every review mode explains what to run; clicks and
    leaving do nothing harmful."""
    settings = viewer_settings(tmp_path)
    engine = new_engine(settings)
    users = add_users(engine)
    gx, gy = np.meshgrid(np.arange(0, 40, 0.5), np.arange(0, 20, 0.5), indexing="ij")
    points = np.stack([gx.ravel(), gy.ravel(), 0.01 * gx.ravel()], axis=1) + [600_000, 5e6, 80]
    path = write_ply(tmp_path / "plain.ply", points)
    with Session(engine) as session:
        survey = register_opened_survey(
            session, open_survey(path, "ply"), format="ply", source_path=path
        )
    driver = Driver(settings, engine)
    try:
        connection = driver.connect(*users["rev"], survey.id)
        expected = {
            "Clutter review": "No clutter run",
            "Guardrail review": "No guardrail run",
            "Model inspection": "No guardrail run",
            "QA": "No clutter or phantom run",
        }
        click = SceneClickEvent(
            client=connection.session.client,
            client_id=connection.session.client.client_id,
            ray_origin=(0.0, 0.0, 10.0),
            ray_direction=(0.0, 0.0, -1.0),
            screen_pos=((0.5, 0.5),),
            modifier=None,
        )
        for name, text in expected.items():
            mark = connection.mark()
            mode = connection.switch(name)
            connection.wait(
                lambda m, t=text: (
                    m.get("type") == "GuiMarkdownMessage" and t in m["props"]["_markdown"]
                ),
                mark,
            )
            connection.call(mode.on_click, click)
        connection.switch("Pillar labelling")  # leaving each of them worked
    finally:
        driver.close()
        engine.dispose()
