"""A full disk (issue 15, section 5) through a real server: below MMSCLEAN_MIN_FREE_MB writes
answer 507 naming the free space while reads and login go on and /health says `degraded`; a
write that really runs out of space (a small tmpfs as the data dir, where this machine lets the
tests mount one) is 507 too and leaves no partial upload behind."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from app.store.pillar_labels import STORE_GRID
from tests.api.server import Server

FULL = "the data directory's disk is full ("


def assert_disk_full(response: httpx.Response) -> None:
    what = f"{response.request.method} {response.request.url.path}"
    assert response.status_code == 507, f"{what}: {response.status_code} {response.text}"
    assert response.json()["detail"].startswith(FULL), response.text


@pytest.fixture(scope="module")
def low_disk(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server whose minimum free space (1 PB) is more than any disk has."""
    data_dir = tmp_path_factory.mktemp("low-disk") / "var"
    running = Server(data_dir, env={"MMSCLEAN_MIN_FREE_MB": str(10**9)}).start()
    yield running
    running.stop()


@pytest.fixture(scope="module")
def admin(low_disk: Server) -> Iterator[httpx.Client]:
    with low_disk.client() as client:
        yield client


def test_health_is_degraded_but_answers(low_disk: Server) -> None:
    response = httpx.get(f"{low_disk.url}/health")
    assert response.status_code == 200
    body = response.json()
    assert body["status"] == "degraded"
    assert FULL in body["detail"] and body["disk_free_mb"] > 0


def test_login_and_reads_keep_working(low_disk: Server, admin: httpx.Client) -> None:
    again = httpx.post(
        f"{low_disk.url}/auth/login",
        json={"username": "admin", "password": "admin-password-1"},
    )
    assert again.status_code == 200, again.text
    assert admin.get("/surveys").status_code == 200
    assert admin.get("/surveys/1").status_code == 200
    assert admin.get("/jobs").status_code == 200
    assert admin.get("/surveys/1/pillars/stats").status_code == 200


@pytest.mark.parametrize(
    "method,url,kwargs",
    [
        ("POST", "/surveys/upload?filename=map.laz", {"content": b"x" * 1000}),
        ("PUT", "/surveys/1/pillars/labels", {"json": {"labels": [{"cell_id": 5, "label": 1}]}}),
        ("POST", "/jobs", {"json": {"kind": "run:phantom", "survey_id": 1}}),
        ("POST", "/users", {"json": {"username": "x", "password": "password-123"}}),
        ("POST", "/surveys/import", {"json": {"path": "anything"}}),
    ],
)
def test_writes_answer_507(admin: httpx.Client, method: str, url: str, kwargs: dict) -> None:
    assert_disk_full(admin.request(method, url, **kwargs))


def test_nothing_was_written(low_disk: Server, admin: httpx.Client) -> None:
    assert admin.get("/jobs").json() == []
    assert sum(admin.get("/surveys/1/pillars/stats").json()["human"]) == 0
    assert not (low_disk.data_dir / "surveys").exists() or not any(
        (low_disk.data_dir / "surveys").iterdir()
    )


def test_the_schema_lists_507_on_guarded_writes(admin: httpx.Client) -> None:
    paths = admin.get("/openapi.json").json()["paths"]
    assert "507" in paths["/surveys/upload"]["post"]["responses"]
    assert "507" in paths["/surveys/{survey_id}/pillars/labels"]["put"]["responses"]
    assert "507" not in paths["/auth/login"]["post"]["responses"]
    assert "507" not in paths["/surveys/{survey_id}/pillars/labels"]["get"]["responses"]


# --- a disk that really is full -------------------------------------------------------------


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 12 MB tmpfs (needs root and a kernel that lets the tests mount one)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=12m", "tmpfs", str(mount)], capture_output=True
    )
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.decode().strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def fill_up(folder: Path) -> None:
    """Write until the disk has no space left."""
    with (folder / "filler").open("wb") as out:
        try:
            while True:
                out.write(b"\0" * 65536)
                out.flush()
        except OSError:
            pass


def test_running_out_of_space_is_507_and_leaves_no_partial_upload(small_disk: Path) -> None:
    data_dir = small_disk / "var"
    server = Server(data_dir, env={"MMSCLEAN_MIN_FREE_MB": "0", "MMSCLEAN_WORKERS": "1"})
    server.start()
    try:
        with server.client() as admin:
            upload = admin.post(
                "/surveys/upload", params={"filename": "big.laz"}, content=b"\0" * (16 * 2**20)
            )
            assert_disk_full(upload)
            surveys_dir = data_dir / "surveys"
            assert not surveys_dir.exists() or not any(surveys_dir.iterdir())
            fill_up(small_disk)
            ix, iy = np.meshgrid(np.arange(300), np.arange(300))
            cells = STORE_GRID.cell_id(ix.ravel(), iy.ravel()).tolist()
            labels = [{"cell_id": c, "label": 0} for c in cells]
            assert_disk_full(admin.put("/surveys/1/pillars/labels", json={"labels": labels}))
            assert admin.get("/surveys/1").status_code == 200  # reads go on
            assert admin.get("/surveys/1/pillars/stats").status_code == 200
    finally:
        server.stop()
    assert "Traceback" not in server.log(), server.log()
