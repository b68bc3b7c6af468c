"""`mmsclean user add` creates a user whose password (read from stdin) logs in to the server."""

from __future__ import annotations

import subprocess
from pathlib import Path

import httpx

from tests.api.server import Server
from tests.cli import mmsclean


def user_add(data_dir: Path, *args: str, password: str) -> subprocess.CompletedProcess:
    env = {"MMSCLEAN_DATA_DIR": str(data_dir)}
    return mmsclean("user", "add", *args, input=password + "\n", env=env, timeout=120)


def test_user_added_on_the_command_line_logs_in(tmp_path: Path) -> None:
    data_dir = tmp_path / "var"
    made = user_add(data_dir, "rita", "--role", "reviewer", password="stdin-secret-1")
    assert made.returncode == 0, made.stderr
    assert "stdin-secret-1" not in made.stdout + made.stderr
    again = user_add(data_dir, "rita", password="stdin-secret-2")
    assert again.returncode != 0 and again.stderr.strip() == "error: user 'rita' already exists"
    bad_role = user_add(data_dir, "sam", "--role", "boss", password="stdin-secret-3")
    assert bad_role.returncode != 0 and "--role: must be one of" in bad_role.stderr
    short = user_add(data_dir, "sam", password="short")
    assert short.returncode != 0 and "password: must have at least 8" in short.stderr

    server = Server(data_dir, env={"MMSCLEAN_SAMPLE_DIR": ""}).start()
    try:
        with server.client("rita", "stdin-secret-1") as rita:
            assert rita.get("/auth/me").json()["role"] == "reviewer"
        wrong = httpx.post(
            f"{server.url}/auth/login", json={"username": "rita", "password": "stdin-secret-2"}
        )
        assert wrong.status_code == 401
    finally:
        server.stop()
