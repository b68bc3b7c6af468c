"""What the API answers to an exception no route handled: a full disk (ENOSPC, SQLite's
"database or disk is full") is 507 with the free space, a name the file system refuses 422,
anything else a generic JSON 500 whose traceback is logged; a background task's failure after
the answer is logged and changes nothing. The exceptions are raised on purpose by a small app
(the point is the mapping, which no well-behaved route of the real server reaches)."""

from __future__ import annotations

import errno
import logging
import sqlite3
from pathlib import Path

import pytest
from fastapi import BackgroundTasks, FastAPI
from fastapi.testclient import TestClient
from sqlalchemy.exc import OperationalError

from app.api.disk_space import DiskSpace
from app.api.errors import install_error_handlers


def disk_full_sqlite() -> None:
    try:
        raise sqlite3.OperationalError("database or disk is full")
    except sqlite3.OperationalError as exc:
        raise OperationalError("INSERT INTO audit_event ...", {}, exc) from exc


def fail_later() -> None:
    raise RuntimeError("background task failed")


@pytest.fixture
def client(tmp_path: Path) -> TestClient:
    app = FastAPI()
    app.state.disk_space = DiskSpace(tmp_path, min_free_mb=0)
    install_error_handlers(app)

    @app.post("/enospc")
    def enospc() -> None:
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "upload"))

    @app.post("/sqlite-full")
    def sqlite_full() -> None:
        disk_full_sqlite()

    @app.get("/too-long")
    def too_long() -> None:
        raise OSError(errno.ENAMETOOLONG, "File name too long", "a" * 300)

    @app.get("/bug")
    def bug() -> None:
        raise KeyError("secret internals")

    @app.get("/after")
    def after(background: BackgroundTasks) -> dict:
        background.add_task(fail_later)
        return {"ok": True}

    return TestClient(app, raise_server_exceptions=False)


@pytest.mark.parametrize("url", ["/enospc", "/sqlite-full"])
def test_a_full_disk_is_507_with_the_free_space(client: TestClient, url: str) -> None:
    response = client.post(url)
    assert response.status_code == 507
    detail = response.json()["detail"]
    assert detail.startswith("the data directory's disk is full (") and "MB free)" in detail


def test_a_name_too_long_is_422(client: TestClient) -> None:
    response = client.get("/too-long")
    assert response.status_code == 422
    assert "too long" in response.json()["detail"]


def test_anything_else_is_a_generic_json_500_logged_with_its_traceback(
    client: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.ERROR, logger="app.api.errors"):
        response = client.get("/bug")
    assert response.status_code == 500
    assert response.headers["content-type"] == "application/json"
    assert response.json() == {"detail": "internal error: the server logged the details"}
    assert "secret internals" not in response.text
    record = next(r for r in caplog.records if "GET /bug" in r.getMessage())
    assert record.exc_info is not None and "KeyError" in caplog.text


def test_a_background_failure_after_the_answer_is_logged_only(
    client: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.ERROR, logger="app.api.errors"):
        response = client.get("/after")
    assert response.status_code == 200 and response.json() == {"ok": True}
    assert "background task failed" in caplog.text
