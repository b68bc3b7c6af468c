"""Acceptance test of the job system: kill -9 the server while a phantom job runs and labels
are being written; after a restart on the same data dir every acknowledged label is there, the
job is interrupted, and resuming it finishes it."""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from app.store.pillar_labels import STORE_GRID
from tests.api.server import Server

TIMEOUT = 300.0
BATCH = 50
ROW = 2000  # cells per grid row the writer fills before the next row


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Server]:
    """A server with the sample survey; no automatic retraining to compete for the workers."""
    running = Server(tmp_path / "var", env={"MMSCLEAN_RETRAIN_EVERY": "0"}).start()
    yield running
    running.stop()


def query(server: Server, sql: str, *args: object) -> list[tuple]:
    with sqlite3.connect(server.data_dir / "mmsclean.sqlite3") as db:
        return db.execute(sql, args).fetchall()


def batch_cells(batch: int) -> tuple[np.ndarray, np.ndarray]:
    """The pillars of the writer's batch `batch` (each pillar written once) and their labels."""
    n = batch * BATCH + np.arange(BATCH)
    ix, iy = n % ROW, n // ROW
    return STORE_GRID.cell_id(ix, iy), (ix + iy) % 4


def wait_job(client: httpx.Client, job_id: int, until) -> dict:
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if until(job):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id}: {job['status']} {job['message']}")


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")


class LabelWriter(threading.Thread):
    """Writes batches of human pillar labels until the server goes away; remembers which
    batches the server acknowledged (200)."""

    def __init__(self, server: Server, survey_id: int):
        super().__init__(daemon=True)
        self.client = server.client()
        self.path = f"/surveys/{survey_id}/pillars/labels"
        self.acknowledged: list[int] = []
        self.refused: list[str] = []

    def run(self) -> None:
        batch = 0
        while True:
            cells, labels = batch_cells(batch)
            body = {
                "labels": [
                    {"cell_id": c, "label": v}
                    for c, v in zip(cells.tolist(), labels.tolist(), strict=True)
                ]
            }
            try:
                response = self.client.put(self.path, json=body, timeout=30)
            except httpx.TransportError:
                return  # killed mid-request: this batch may or may not be stored
            if response.status_code != 200:
                self.refused.append(f"{response.status_code} {response.text}")
                return
            assert response.json()["written"] == BATCH
            self.acknowledged.append(batch)
            batch += 1


def test_kill_9_mid_job_and_mid_writes(server: Server) -> None:
    (survey_id,) = query(server, "SELECT id FROM survey ORDER BY id LIMIT 1")[0]
    with server.client() as admin:
        created = admin.post("/jobs", json={"kind": "run:phantom", "survey_id": survey_id})
        assert created.status_code == 201, created.text
        job_id = created.json()["id"]
        writer = LabelWriter(server, survey_id)
        writer.start()
        running = wait_job(
            admin,
            job_id,
            lambda j: (
                j["status"] not in ("queued", "running")
                or (j["progress"] >= 0.15 and len(writer.acknowledged) >= 10)
            ),
        )
        assert running["status"] == "running", running["message"]  # in the CNN stage
    worker_pid = running["worker_pid"]

    server.kill_9()
    writer.join(60)
    assert not writer.is_alive() and writer.refused == []
    assert len(writer.acknowledged) >= 10
    deadline = time.monotonic() + 10
    while alive(worker_pid):  # the worker died with its server
        assert time.monotonic() < deadline, f"worker {worker_pid} outlived the server"
        time.sleep(0.1)
    assert query(server, "SELECT status FROM job WHERE id = ?", job_id) == [("running",)]

    server.start()
    with server.client() as admin:
        job = admin.get(f"/jobs/{job_id}").json()
        assert job["status"] == "interrupted"
        assert "server stopped while it ran" in job["message"]

        # every label whose write was acknowledged survived
        cells = np.concatenate([batch_cells(b)[0] for b in writer.acknowledged])
        labels = np.concatenate([batch_cells(b)[1] for b in writer.acknowledged])
        ix, iy = STORE_GRID.decode(cells)
        centres = STORE_GRID.cell_center(ix, iy)
        (x0, y0), (x1, y1) = centres.min(axis=0), centres.max(axis=0)
        tile = admin.get(
            f"/surveys/{survey_id}/pillars/labels",
            params={"source": "human", "x0": x0, "y0": y0, "x1": x1, "y1": y1},
        )
        assert tile.status_code == 200, tile.text
        stored = dict(zip(tile.json()["cell_id"], tile.json()["label"], strict=True))
        missing = [c for c in cells.tolist() if c not in stored]
        assert missing == [], f"{len(missing)} acknowledged labels lost"
        assert [stored[c] for c in cells.tolist()] == labels.tolist()

        resumed = admin.post(f"/jobs/{job_id}/resume")
        assert resumed.status_code == 200, resumed.text
        assert resumed.json()["status"] in ("queued", "running")
        done = wait_job(admin, job_id, lambda j: j["status"] not in ("queued", "running"))
        assert done["status"] == "succeeded", done["message"]
        assert done["attempts"] == 2 and done["id"] == job_id
        log = admin.get(f"/jobs/{job_id}/log").text
        assert "attempt 1 of job" in log and "attempt 2 of job" in log
    (count,) = query(
        server, "SELECT COUNT(*) FROM pillar_label WHERE survey_id = ? AND source = 'model'",
        survey_id,
    )[0]  # fmt: skip
    assert count == done["result"]["counts"]["model_labels"] > 0
