"""A real server: `mmsclean serve` on a free port answers /health from its SQLite database and
prints only its own address."""

from __future__ import annotations

import os
import re
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import httpx


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_answers_health(tmp_path: Path) -> None:
    port = free_port()
    data_dir = tmp_path / "var"
    env = {**os.environ, "MMSCLEAN_DATA_DIR": str(data_dir)}
    server = subprocess.Popen(
        [sys.executable, "-m", "app", "serve", "--host", "127.0.0.1", "--port", str(port)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 60
        response = None
        while time.monotonic() < deadline:
            try:
                response = httpx.get(f"http://127.0.0.1:{port}/health", timeout=2)
                break
            except httpx.TransportError:
                assert server.poll() is None, server.stdout.read().decode()
                time.sleep(0.2)
        assert response is not None, "server did not answer within 60 s"
        assert response.status_code == 200
        assert response.json()["status"] == "ok"
        assert httpx.get(f"http://127.0.0.1:{port}/nothing", timeout=2).status_code == 404
    finally:
        server.terminate()
        server.wait(timeout=20)
    # the viewer's loopback port serves an empty scene without a login: never printed (issue 20)
    output = server.stdout.read().decode()
    printed = {int(p) for p in re.findall(r"(?:https?|wss?)://[\w.\-]+:(\d+)", output)}
    assert printed == {port}, output
    database = data_dir / "mmsclean.sqlite3"
    assert database.is_file()
    with sqlite3.connect(database) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    assert {"survey", "frame", "job", "user", "audit_event", "pillar_label"} <= {
        t.lower() for t in tables
    }
