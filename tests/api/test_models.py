"""Model versions, promotion, retraining on demand and by the new-labels trigger (real server)."""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from app.store.pillar_labels import STORE_GRID
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
            " origin_y, origin_z, sensor_kind, sensor_note) VALUES (datetime('now'),"
            " datetime('now'), 1, 'm', 'sim', '/m', 0, 0, 0, 0, 0, 0, 0, 'profile', 'declared')"
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


def trainable_labels(n: int, first: int = 0) -> list[dict]:
    """N pillar labels that could train: a strip 0.2 m wide and N * 0.2 m long (several 10 m
    blocks once N > 100), ground and phantom alternating."""
    ix = np.arange(first, first + n)
    cells = STORE_GRID.cell_id(ix, np.zeros(n, dtype=np.int64)).tolist()
    return [{"cell_id": c, "label": 3 * (i % 2)} for i, c in zip(ix.tolist(), cells, strict=True)]


def test_new_labels_queue_retraining_once(trigger_server: Server) -> None:
    survey = add_survey(trigger_server)
    strip = np.arange(0, 303)  # its phantom run saw points along the labelled strip
    add_model_labels(trigger_server, survey, strip, np.zeros_like(strip))
    anna = trigger_server.add_user("trigger-anna", "annotator")
    labels = trainable_labels(3)
    assert anna.put(f"/surveys/{survey}/pillars/labels", json={"labels": labels}).is_success
    with trigger_server.client() as admin:
        time.sleep(0.5)
        assert train_jobs(admin) == []  # 3 < 5
        status = admin.get("/models/retraining").json()
        expected = {"threshold": 5, "new_labels": 3, "pending_job_id": None, "blocked_by": None}
        assert {k: status[k] for k in expected} == expected
        # on demand: 3 labels cannot train, and the button's line says why (issue 20)
        phantom = next(p for p in status["pipelines"] if p["pipeline"] == "phantom")
        assert phantom["blocked_by"] == "3 human pillar labels; retraining needs at least 50"
        guardrail = next(p for p in status["pipelines"] if p["pipeline"] == "guardrail")
        assert guardrail["blocked_by"] == "0 reviewed guardrail slices; retraining needs 20"
        refused = admin.post("/models/retrain", json={"pipeline": "phantom"})
        assert refused.status_code == 422 and "retraining needs at least 50" in refused.text
        more = trainable_labels(300, first=3)
        assert anna.put(f"/surveys/{survey}/pillars/labels", json={"labels": more}).is_success
        deadline = time.monotonic() + 10
        while not train_jobs(admin) and time.monotonic() < deadline:
            time.sleep(0.1)
        jobs = train_jobs(admin)
        assert len(jobs) == 1 and jobs[0]["config"] == {"trigger": "labels"}
        # the labels count as used once a training succeeds, not when it is queued (a failed
        # one reset the counter, issue 20); the pending job keeps the trigger from firing again
        status = admin.get("/models/retraining").json()
        assert status["new_labels"] == 303 and status["pending_job_id"] == jobs[0]["id"]
    anna.close()


@pytest.fixture(scope="module")
def blocked_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server whose trigger fires every 1,000 new human labels (no workers needed)."""
    data_dir: Path = tmp_path_factory.mktemp("models-blocked") / "var"
    env = {"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_RETRAIN_EVERY": "1000", "MMSCLEAN_WORKERS": "1"}
    running = Server(data_dir, env=env).start()
    yield running
    running.stop()


def add_model_labels(server: Server, survey: int, ix: np.ndarray, iy: np.ndarray) -> None:
    """Model pre-labels, as a phantom run stores them for the pillars it found points in."""
    cells = STORE_GRID.cell_id(ix, iy).tolist()
    with database(server) as conn:
        conn.executemany(
            "INSERT INTO pillar_label (created_at, updated_at, version, survey_id, cell_id, label,"
            " source, confidence) VALUES (datetime('now'), datetime('now'), 1, ?, ?, 0, 'model',"
            " 0.9)",
            [(survey, c) for c in cells],
        )


def settled_status(admin) -> dict:
    """GET /models/retraining once the trigger has had its turn after the last write."""
    time.sleep(1.0)
    return admin.get("/models/retraining").json()


def test_labels_that_cannot_train_queue_nothing_and_say_why(blocked_server: Server) -> None:
    """The issue: 100,000 labels from one annotator on one survey queued a train:phantom that
    failed with "need at least one array to concatenate" (the labelled pillars held no points).
    Now the trigger checks the task's prerequisites first and reports what blocks it."""
    mapped = add_survey(blocked_server)
    grid = np.mgrid[0:100, 0:100].reshape(2, -1)  # its phantom run saw points in 20 m x 20 m
    add_model_labels(blocked_server, mapped, grid[0], grid[1])
    anna = blocked_server.add_user("blocked-anna", "annotator")
    ix, iy = np.mgrid[1000:1400, 0:250].reshape(2, -1)  # 100,000 pillars 200 m away
    cells = STORE_GRID.cell_id(ix, iy).tolist()
    labels = [{"cell_id": c, "label": 3 * (i % 2)} for i, c in enumerate(cells)]
    assert anna.put(f"/surveys/{mapped}/pillars/labels", json={"labels": labels}).is_success
    with blocked_server.client() as admin:
        status = settled_status(admin)
        assert status["new_labels"] == 100_000 and status["pending_job_id"] is None
        assert "has points in its survey's map" in status["blocked_by"]
        assert train_jobs(admin) == []
        # a survey no phantom run mapped: which labelled pillars hold points is unknown, so
        # its labels count for nothing (the bench's 100,000 labels on an unrun survey queued a
        # job that then failed)
        other = add_survey(blocked_server)
        ground = [{**label, "label": 0} for label in trainable_labels(1000)]
        assert anna.put(f"/surveys/{other}/pillars/labels", json={"labels": ground}).is_success
        status = settled_status(admin)
        assert "1,000 labels lie on surveys no phantom run has mapped" in status["blocked_by"]
        assert train_jobs(admin) == []
        # once its phantom run has mapped it: one class only, still nothing to learn
        strip = np.arange(0, 3000)
        add_model_labels(blocked_server, other, strip, np.zeros_like(strip))
        assert anna.put(f"/surveys/{other}/pillars/labels", json={"labels": ground}).is_success
        status = settled_status(admin)
        assert status["blocked_by"] == (
            "the training labels hold 1 class(es) (ground); retraining needs at least 2"
        )
        assert train_jobs(admin) == []
        # phantoms labelled there too: now it can train, and the trigger queues it
        phantoms = [{**label, "label": 3} for label in trainable_labels(1000, first=2000)]
        assert anna.put(f"/surveys/{other}/pillars/labels", json={"labels": phantoms}).is_success
        deadline = time.monotonic() + 10
        while not train_jobs(admin) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert [j["config"] for j in train_jobs(admin)] == [{"trigger": "labels"}]
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


def test_the_segmentation_weights_are_reported_where_they_belong(tmp_path: Path) -> None:
    """Without the ESPNetv2 weights the server says so, with the file it looks for and where
    to get it (the dashboard unticks the camera option with that, issue 20)."""
    empty = tmp_path / "weights"
    empty.mkdir()
    env = {"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_WEIGHTS_DIR": str(empty)}
    running = Server(tmp_path / "var", env=env).start()
    try:
        with running.client() as client:
            answer = client.get("/models/segmentation")
            assert answer.status_code == 200, answer.text
            weights = answer.json()
            assert weights["available"] is False
            assert weights["file"] == str(empty / "espnetv2_s_2.0_city_1024x512.pth")
            assert "sacmehta/EdgeNets" in weights["upstream"]
            (empty / "espnetv2_s_2.0_city_1024x512.pth").write_bytes(b"\0")
            assert client.get("/models/segmentation").json()["available"] is True
    finally:
        running.stop()
