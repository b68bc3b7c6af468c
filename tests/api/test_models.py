"""Model versions, promotion, retraining on demand and by the new-labels trigger (real server)."""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.server import Server


@pytest.fixture(scope="module")
def trigger_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server whose retraining trigger fires every 5 new human labels."""
    data_dir: Path = tmp_path_factory.mktemp("models") / "var"
    env = {"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_RETRAIN_EVERY": "5", "MMSCLEAN_WORKERS": "1"}
    running = Server(data_dir, env=env).start()
    yield running
    running.stop()


def database(server: Server) -> sqlite3.Connection:
    return sqlite3.connect(server.data_dir / "mmsclean.sqlite3")


def add_survey(server: Server) -> int:
    with database(server) as conn:
        return conn.execute(
            "INSERT INTO survey (created_at, updated_at, version, name, format, source_path,"
            " frame_count, point_count, has_reference_labels, poses_estimated, origin_x,"
            " origin_y, origin_z) VALUES (datetime('now'), datetime('now'), 1, 'm', 'sim', '/m',"
            " 0, 0, 0, 0, 0, 0, 0)"
        ).lastrowid


def add_version(server: Server, name: str, promoted: bool) -> int:
    with database(server) as conn:
        return conn.execute(
            "INSERT INTO model_version (created_at, updated_at, version, pipeline, name,"
            " checkpoint_path, metrics, trained_on, is_promoted) VALUES (datetime('now'),"
            " datetime('now'), 1, 'phantom', ?, '/x.pt', '{\"validation\": {}}', '{}', ?)",
            (name, int(promoted)),
        ).lastrowid


def train_jobs(client) -> list[dict]:
    return [j for j in client.get("/jobs").json() if j["kind"] == "train:phantom"]


def test_new_labels_queue_retraining_once(trigger_server: Server) -> None:
    survey = add_survey(trigger_server)
    anna = trigger_server.add_user("trigger-anna", "annotator")
    labels = [{"cell_id": c, "label": c % 4} for c in range(3)]
    assert anna.put(f"/surveys/{survey}/pillars/labels", json={"labels": labels}).is_success
    with trigger_server.client() as admin:
        time.sleep(0.5)
        assert train_jobs(admin) == []  # 3 < 5
        status = admin.get("/models/retraining").json()
        assert status == {"threshold": 5, "new_labels": 3, "pending_job_id": None}
        more = [{"cell_id": c, "label": 1} for c in range(3, 6)]
        assert anna.put(f"/surveys/{survey}/pillars/labels", json={"labels": more}).is_success
        deadline = time.monotonic() + 10
        while not train_jobs(admin) and time.monotonic() < deadline:
            time.sleep(0.1)
        jobs = train_jobs(admin)
        assert len(jobs) == 1 and jobs[0]["config"] == {"trigger": "labels"}
        # the counter starts again from that job
        assert admin.get("/models/retraining").json()["new_labels"] == 0
    anna.close()


def test_retrain_on_demand_needs_admin(trigger_server: Server) -> None:
    reviewer = trigger_server.add_user("models-rev", "reviewer")
    refused = reviewer.post("/models/retrain", json={"pipeline": "phantom"})
    assert refused.status_code == 403
    reviewer.close()
    with trigger_server.client() as admin:
        queued = admin.post("/models/retrain", json={"pipeline": "phantom", "config": {}})
        assert queued.status_code == 202 and queued.json()["kind"] == "train:phantom"
        bad = admin.post("/models/retrain", json={"pipeline": "phantom", "config": {"epochs": 0}})
        assert bad.status_code == 422 and "epochs" in bad.json()["detail"]
        clutter = admin.post("/models/retrain", json={"pipeline": "clutter"})
        assert clutter.status_code == 422 and clutter.json()["detail"].startswith("pipeline:")


def test_admin_promotes_a_version(trigger_server: Server) -> None:
    old = add_version(trigger_server, "old", promoted=True)
    new = add_version(trigger_server, "new", promoted=False)
    with trigger_server.client() as admin:
        listed = admin.get("/models", params={"pipeline": "phantom"}).json()
        assert {m["name"] for m in listed} >= {"old", "new"}
        assert admin.post(f"/models/{new}/promote").json()["is_promoted"] is True
        assert admin.get(f"/models/{old}").json()["is_promoted"] is False
        assert admin.get("/models/999").status_code == 404
        assert admin.post("/models/999/promote").status_code == 404
    annotator = trigger_server.add_user("models-ann", "annotator")
    assert annotator.post(f"/models/{old}/promote").status_code == 403
    annotator.close()
