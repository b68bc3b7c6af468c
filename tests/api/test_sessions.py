"""Login sessions, login throttling, tokens kept out of the logs and private data files, on real
servers: a token stops working the moment its session ends (logout, revocation, a change to the
user), in HTTP requests and in the viewer's websocket alike."""

from __future__ import annotations

import asyncio
import base64
import json
import stat
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import httpx
import pytest
import viser
from sqlalchemy.engine import Engine
from sqlmodel import Session, select
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from app.store.db import make_engine
from app.store.models import AuditEvent, AuthSession, utcnow
from tests.api.server import ADMIN_PASSWORD, Server

SUBPROTOCOL = f"viser-v{viser.__version__}"
PASSWORD = "password-123"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """An empty server whose open viewers check their login twice a second."""
    data_dir = tmp_path_factory.mktemp("sessions") / "var"
    env = {"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_VIEWER_SESSION_CHECK_S": "0.5"}
    running = Server(data_dir, env=env).start()
    yield running
    running.stop()


@pytest.fixture(scope="module")
def engine(server: Server) -> Iterator[Engine]:
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    yield engine
    engine.dispose()


@pytest.fixture(scope="module")
def users(server: Server) -> dict[str, int]:
    """Users for these tests: name -> id."""
    ids = {}
    with server.client() as admin:
        for name in ("sam", "tess", "ursula", "viv"):
            response = admin.post("/users", json={"username": name, "password": PASSWORD})
            ids[name] = response.json()["id"]
    return ids


def log_in(server: Server, name: str, agent: str = "pytest") -> tuple[str, httpx.Client]:
    """A bearer token of a new session, and a client that sends it."""
    password = ADMIN_PASSWORD if name == "admin" else PASSWORD
    response = httpx.post(
        f"{server.url}/auth/login",
        json={"username": name, "password": password},
        headers={"User-Agent": agent},
    )
    assert response.status_code == 200, response.text
    token = response.json()["access_token"]
    headers = {"Authorization": f"Bearer {token}", "User-Agent": agent}
    return token, httpx.Client(base_url=server.url, headers=headers, timeout=30)


def me(client: httpx.Client) -> int:
    return client.get("/auth/me").status_code


def claims(token: str) -> dict:
    payload = token.split(".")[0]
    return json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))


# --- sessions ------------------------------------------------------------------------------


def test_logout_ends_the_token_and_the_cookie(server: Server, users: dict[str, int]) -> None:
    token, client = log_in(server, "sam")
    with client:
        assert me(client) == 200
        out = client.post("/auth/logout")
        assert out.status_code == 204
        assert 'mmsclean_token=""' in out.headers["set-cookie"]  # the cookie is cleared
        assert me(client) == 401
        cookie_only = httpx.get(f"{server.url}/auth/me", cookies={"mmsclean_token": token})
        assert cookie_only.status_code == 401


def test_sessions_are_listed_and_revoked_by_their_user(
    server: Server, users: dict[str, int]
) -> None:
    first_token, first = log_in(server, "tess", agent="laptop")
    _, second = log_in(server, "tess", agent="tablet")
    _, other_user = log_in(server, "ursula")
    with first, second, other_user:
        listed = first.get("/auth/sessions").json()
        assert [s["user_agent"] for s in listed] == ["tablet", "laptop"]  # newest first
        assert [s["current"] for s in listed] == [False, True]
        assert listed[1]["id"] == claims(first_token)["s"]
        assert listed[0]["client_address"] == "127.0.0.1"
        assert {"created_at", "last_seen_at", "expires_at"} <= set(listed[0])

        tablet = listed[0]["id"]
        assert other_user.delete(f"/auth/sessions/{tablet}").status_code == 404  # not theirs
        assert me(second) == 200
        assert first.delete(f"/auth/sessions/{tablet}").status_code == 204
        assert me(second) == 401 and me(first) == 200
        assert first.delete(f"/auth/sessions/{tablet}").status_code == 404  # already ended

        _, third = log_in(server, "tess", agent="phone")
        with third:
            ended = first.delete("/auth/sessions")
            assert ended.status_code == 200 and ended.json() == {"ended": 1}
            assert me(third) == 401 and me(first) == 200
        assert [s["user_agent"] for s in first.get("/auth/sessions").json()] == ["laptop"]
        assert me(other_user) == 200  # another user's sessions are untouched


def test_admins_list_and_end_a_users_sessions(server: Server, users: dict[str, int]) -> None:
    _, client = log_in(server, "viv")
    _, other = log_in(server, "viv")
    with server.client() as admin, client, other:
        listed = admin.get(f"/users/{users['viv']}/sessions").json()
        assert len(listed) == 2 and not any(s["current"] for s in listed)
        assert client.get(f"/users/{users['viv']}/sessions").status_code == 403
        assert admin.delete(f"/users/{users['viv']}/sessions/{listed[0]['id']}").status_code == 204
        assert me(other) == 401 and me(client) == 200
        ended = admin.delete(f"/users/{users['viv']}/sessions")
        assert ended.json() == {"ended": 1} and me(client) == 401
        assert admin.get("/users/9999/sessions").status_code == 404


@pytest.mark.parametrize(
    "change",
    [{"password": "password-456"}, {"role": "reviewer"}, {"is_active": False}],
    ids=["password", "role", "deactivation"],
)
def test_a_change_to_the_user_ends_their_sessions(
    server: Server, users: dict[str, int], engine: Engine, change: dict
) -> None:
    with server.client() as admin:
        name = f"changed-{next(iter(change))}"
        admin.post("/users", json={"username": name, "password": PASSWORD})
        user_id = next(u["id"] for u in admin.get("/users").json() if u["username"] == name)
        _, client = log_in(server, name)
        with client:
            assert me(client) == 200
            assert admin.patch(f"/users/{user_id}", json=change).status_code == 200
            assert me(client) == 401
    with Session(engine) as session:
        ended = session.exec(select(AuthSession).where(AuthSession.user_id == user_id)).one()
    assert ended.ended_at is not None
    reason = {"password": "password", "role": "role", "is_active": "deactivated"}
    assert ended.end_reason == reason[next(iter(change))]


def test_a_forged_session_id_is_refused(server: Server, users: dict[str, int]) -> None:
    token, client = log_in(server, "sam")
    with client:
        payload = claims(token)
        payload["s"] += 1
        raw = json.dumps(payload, separators=(",", ":")).encode()
        forged_payload = base64.urlsafe_b64encode(raw).rstrip(b"=").decode()
        forged = f"{forged_payload}.{token.split('.')[1]}"
        headers = {"Authorization": f"Bearer {forged}"}
        assert httpx.get(f"{server.url}/auth/me", headers=headers).status_code == 401
        assert me(client) == 200


def test_last_seen_is_written_at_most_once_a_minute(
    server: Server, users: dict[str, int], engine: Engine
) -> None:
    token, client = log_in(server, "sam")
    session_id = claims(token)["s"]

    def last_seen() -> object:
        with Session(engine) as session:
            return session.get(AuthSession, session_id).last_seen_at

    with client:
        at_login = last_seen()
        for _ in range(5):
            assert me(client) == 200
        assert last_seen() == at_login  # reads did not write
        earlier = utcnow() - timedelta(minutes=2)
        with Session(engine) as session:
            row = session.get(AuthSession, session_id)
            row.last_seen_at = earlier
            session.add(row)
            session.commit()
        assert me(client) == 200
        moved = last_seen()
        assert moved > earlier + timedelta(minutes=1)
        assert me(client) == 200
        assert last_seen() == moved


def test_the_viewer_websocket_follows_the_session(server: Server, users: dict[str, int]) -> None:
    """An open viewer closes (1008) once its login session ends; the token then opens none."""
    token, client = log_in(server, "sam")
    url = f"ws://127.0.0.1:{server.port}/viewer/ws"

    async def open_then_log_out() -> tuple[int | None, str]:
        bearer = {"Authorization": f"Bearer {token}"}
        async with connect(url, additional_headers=bearer, subprotocols=[SUBPROTOCOL]) as ws:
            assert (await asyncio.to_thread(client.post, "/auth/logout")).status_code == 204
            try:
                async with asyncio.timeout(60):
                    while True:
                        await ws.recv()
            except ConnectionClosed:
                pass
            return ws.close_code, ws.close_reason

    async def refused() -> int:
        try:
            async with connect(f"{url}?token={token}", subprotocols=[SUBPROTOCOL]):
                return 101
        except InvalidStatus as exc:
            return exc.response.status_code

    with client:
        assert asyncio.run(open_then_log_out()) == (1008, "login session ended")
        assert asyncio.run(refused()) == 403


# --- tokens stay out of the logs ----------------------------------------------------------------


def test_tokens_are_redacted_from_the_server_log(server: Server, users: dict[str, int]) -> None:
    token, client = log_in(server, "sam")
    signature = token.split(".")[1]

    async def viewer_with_query_token() -> None:
        url = f"ws://127.0.0.1:{server.port}/viewer/ws?token={token}"
        async with connect(url, subprotocols=[SUBPROTOCOL], max_size=None):
            pass

    with client:
        assert httpx.get(f"{server.url}/auth/me", params={"token": token}).status_code == 401
        httpx.get(f"{server.url}/viewer/ws", params={"token": token, "ticket": "abc"})
        asyncio.run(viewer_with_query_token())
        assert me(client) == 200
    log = server.log()
    assert "/auth/me?token=***" in log  # the access log line is there, its token is not
    assert "WebSocket /viewer/ws?token=***" in log
    assert signature not in log and token not in log
    assert "ticket=abc" not in log


# --- private files ------------------------------------------------------------------------------


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_data_dir_and_database_are_private(server: Server, users: dict[str, int]) -> None:
    """The test made the data dir 0755 before the server started: the server tightened it."""
    assert mode(server.data_dir) == 0o700
    database = server.data_dir / "mmsclean.sqlite3"
    assert mode(database) == 0o600
    companions = [p for p in server.data_dir.glob("mmsclean.sqlite3-*") if p.is_file()]
    assert companions  # WAL mode: -wal and -shm exist while the server runs
    assert {p.name: mode(p) for p in companions} == {p.name: 0o600 for p in companions}
    assert mode(server.data_dir / "secret.key") == 0o600


# --- login throttling ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def strict(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server that locks a name out after 3 failures and an address after 8, for 60 s."""
    env = {
        "MMSCLEAN_SAMPLE_DIR": "",
        "MMSCLEAN_LOGIN_FREE_FAILURES": "3",
        "MMSCLEAN_LOGIN_ADDRESS_FREE_FAILURES": "8",
        "MMSCLEAN_LOGIN_FIRST_DELAY_S": "60",
    }
    running = Server(tmp_path_factory.mktemp("throttle") / "var", env=env).start()
    with running.client() as admin:
        for name in ("una", "vic"):
            admin.post("/users", json={"username": name, "password": PASSWORD})
    yield running
    running.stop()


def attempt(server: Server, name: str, password: str = "wrong-password") -> httpx.Response:
    return httpx.post(f"{server.url}/auth/login", json={"username": name, "password": password})


def test_failed_logins_lock_out_the_name_then_the_address(strict: Server) -> None:
    # a success clears the name's count: 2 + 2 failures of una never lock her out
    for _ in range(2):
        assert attempt(strict, "una").status_code == 401
    assert attempt(strict, "una", PASSWORD).status_code == 200
    for _ in range(2):
        assert attempt(strict, "una").status_code == 401
    assert attempt(strict, "una", PASSWORD).status_code == 200
    # the third failure of vic locks the name: even the right password waits
    for _ in range(3):
        assert attempt(strict, "vic").status_code == 401
    locked = attempt(strict, "vic", PASSWORD)
    assert locked.status_code == 429
    assert 1 <= int(locked.headers["retry-after"]) <= 60
    assert locked.json()["detail"].startswith("too many failed logins for user 'vic'")
    assert attempt(strict, "una", PASSWORD).status_code == 200  # 7 from this address so far
    # the eighth failure from this address locks it, for every name
    assert attempt(strict, "nobody").status_code == 401
    refused = attempt(strict, "una", PASSWORD)
    assert refused.status_code == 429 and "address 127.0.0.1" in refused.json()["detail"]
    assert int(refused.headers["retry-after"]) >= 1

    engine = make_engine(f"sqlite:///{strict.data_dir / 'mmsclean.sqlite3'}")
    with Session(engine) as session:
        lockouts = session.exec(
            select(AuditEvent.entity_id).where(AuditEvent.action == "auth.lockout")
        ).all()
    engine.dispose()
    assert lockouts == ["user:vic", "address:127.0.0.1"]

    strict.stop()  # the lock-out is in the store: a restart does not lift it
    strict.start()
    assert attempt(strict, "una", PASSWORD).status_code == 429
