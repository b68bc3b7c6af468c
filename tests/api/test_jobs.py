"""`/jobs` on a real server: a phantom run on the sample survey from queue to stored pre-labels,
cancel, requeue, logs and files, and the error answers."""

from __future__ import annotations

import io
import json
import math
import sqlite3
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from app.store.pillar_labels import STORE_GRID
from tests.api.server import Server

TIMEOUT = 300.0
ACTIVE = ("queued", "running")


def database(server: Server) -> sqlite3.Connection:
    return sqlite3.connect(server.data_dir / "mmsclean.sqlite3")


def sample_survey_id(server: Server) -> int:
    with database(server) as db:
        return db.execute("SELECT id FROM survey ORDER BY id LIMIT 1").fetchone()[0]


def model_labels(server: Server, survey_id: int) -> list[tuple]:
    with database(server) as db:
        return db.execute(
            "SELECT cell_id, label, confidence, model_version_id, updated_at FROM pillar_label "
            "WHERE survey_id = ? AND source = 'model' ORDER BY cell_id",
            (survey_id,),
        ).fetchall()


def watch(
    client: httpx.Client, job_id: int, until=lambda j: j["status"] not in ACTIVE
) -> tuple[dict, list[float]]:
    """Poll the job until `until`; returns it and the progress values seen."""
    seen: list[float] = []
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        response = client.get(f"/jobs/{job_id}")
        assert response.status_code == 200, response.text
        job = response.json()
        seen.append(job["progress"])
        if until(job):
            return job, seen
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} is still {job['status']}: {job['message']}")


@pytest.fixture(scope="module")
def admin(sample_server: Server) -> httpx.Client:
    with sample_server.client() as client:
        yield client


def test_phantom_job_runs_and_stores_model_prelabels(
    sample_server: Server, admin: httpx.Client
) -> None:
    survey_id = sample_survey_id(sample_server)
    created = admin.post("/jobs", json={"kind": "run:phantom", "survey_id": survey_id})
    assert created.status_code == 201, created.text
    job_id = created.json()["id"]
    assert created.json()["status"] in ACTIVE

    job, seen = watch(admin, job_id)
    assert job["status"] == "succeeded", job["message"]
    assert any(0.15 < p < 0.85 for p in seen), seen  # watched it rise through the CNN stage
    assert seen == sorted(seen) and job["progress"] == 1.0
    assert job["attempts"] == 1 and job["seconds"] > 0 and job["finished_at"]

    # the pre-labels in the store are the CNN's judged pillars, on the store grid
    counts = job["result"]["counts"]
    rows = model_labels(sample_server, survey_id)
    assert len(rows) == counts["model_labels"] == counts["pillars_classified"] > 0
    with database(sample_server) as db:
        name, promoted = db.execute(
            "SELECT name, is_promoted FROM model_version WHERE id = ?",
            (job["result"]["model_version_id"],),
        ).fetchone()
    assert (name, promoted) == ("shipped:phantom_cnn_context.pt", 1)
    assert {r[3] for r in rows} == {job["result"]["model_version_id"]}
    npz = admin.get(f"/jobs/{job_id}/files/pillars.npz")
    assert npz.status_code == 200
    pillars = np.load(io.BytesIO(npz.content))
    judged = pillars["pillars"][pillars["classified"]]
    probs = pillars["probabilities"][pillars["classified"]]
    expected = dict(
        zip(
            STORE_GRID.cell_id(judged[:, 0], judged[:, 1]).tolist(),
            probs.argmax(axis=1).tolist(),
            strict=True,
        )
    )
    assert {r[0]: r[1] for r in rows} == expected
    assert all(0 < r[2] <= 1 for r in rows)

    # log, results, files
    log = admin.get(f"/jobs/{job_id}/log")
    assert log.status_code == 200 and "attempt 1 of job" in log.text
    assert "succeeded in" in log.text
    last = admin.get(f"/jobs/{job_id}/log", params={"tail": 1})
    assert last.text.count("\n") == 1 and "succeeded in" in last.text
    results = admin.get(f"/jobs/{job_id}/results").json()
    names = {f["name"] for f in results["files"]}
    assert {"report.json", "pillars.npz", "cleaned.laz", "job.log"} <= names
    assert sum(n.startswith("labels/") for n in names) == counts["frames"]
    assert results["result"]["metrics"]["pillar"]
    report = admin.get(f"/jobs/{job_id}/files/report.json")
    assert report.status_code == 200 and report.json()["counts"]["pillars"] == counts["pillars"]
    assert Path(job["result"]["report"]).name == "report.json"
    escape = admin.get(f"/jobs/{job_id}/files/..%2F..%2Fmmsclean.sqlite3")
    assert escape.status_code == 400 and "outside" in escape.json()["detail"]
    assert admin.get(f"/jobs/{job_id}/files/nothing.bin").status_code == 404

    listed = admin.get("/jobs", params={"kind": "run:phantom", "status": "succeeded"}).json()
    assert job_id in [j["id"] for j in listed]
    newest = admin.get("/jobs").json()
    assert [j["id"] for j in newest] == sorted((j["id"] for j in newest), reverse=True)


def test_cancel_a_running_phantom_job_then_requeue(
    sample_server: Server, admin: httpx.Client
) -> None:
    survey_id = sample_survey_id(sample_server)
    before = model_labels(sample_server, survey_id)
    job_id = admin.post("/jobs", json={"kind": "run:phantom", "survey_id": survey_id}).json()["id"]
    watch(admin, job_id, lambda j: j["status"] == "running" and j["progress"] >= 0.15)
    asked = admin.post(f"/jobs/{job_id}/cancel")
    assert asked.status_code == 200, asked.text
    assert asked.json()["cancel_requested"] or asked.json()["status"] == "cancelled"
    job, _ = watch(admin, job_id)
    assert job["status"] == "cancelled" and job["progress"] < 0.9
    assert model_labels(sample_server, survey_id) == before  # nothing half-stored
    again = admin.post(f"/jobs/{job_id}/cancel")
    assert again.status_code == 409 and "already cancelled" in again.json()["detail"]

    copy = admin.post(f"/jobs/{job_id}/requeue")
    assert copy.status_code == 201
    assert copy.json()["id"] != job_id and copy.json()["config"] == job["config"]
    assert admin.post(f"/jobs/{copy.json()['id']}/requeue").status_code == 409  # still active
    admin.post(f"/jobs/{copy.json()['id']}/cancel")
    cancelled, _ = watch(admin, copy.json()["id"])
    assert cancelled["status"] == "cancelled"


def test_errors_name_the_field_or_record(sample_server: Server, admin: httpx.Client) -> None:
    survey_id = sample_survey_id(sample_server)
    unknown = admin.post("/jobs", json={"kind": "run:nothing", "survey_id": survey_id})
    assert unknown.status_code == 422 and unknown.json()["detail"].startswith("kind: unknown")
    for body, field in (
        ({"kind": "run:phantom", "survey_id": survey_id, "config": {"model_path": "/etc/passwd"}},
         "config.model_path"),
        ({"kind": "run:phantom", "survey_id": survey_id, "config": {"cell": 1}}, "config.cell"),
        ({"kind": "run:phantom", "survey_id": 99999}, "survey_id"),
        ({"kind": "run:phantom"}, "survey_id"),
    ):  # fmt: skip
        response = admin.post("/jobs", json=body)
        assert response.status_code == 422, response.text
        assert response.json()["detail"].startswith(f"{field}:")
    for method, path in (
        ("GET", "/jobs/99999"),
        ("GET", "/jobs/99999/log"),
        ("GET", "/jobs/99999/results"),
        ("GET", "/jobs/99999/files/report.json"),
        ("POST", "/jobs/99999/cancel"),
        ("POST", "/jobs/99999/resume"),
        ("POST", "/jobs/99999/requeue"),
    ):
        response = admin.request(method, path)
        assert response.status_code == 404, (method, path)
        assert response.json()["detail"] == "job 99999 not found"
    assert httpx.get(f"{sample_server.url}/jobs").status_code == 401


@pytest.mark.parametrize(
    ("kind", "config", "field", "problem"),
    [  # the values: each passed before, and ran out of memory, time or range later
        ("run:clutter", {"dufomap_resolution": 0.001}, "dufomap_resolution", ">= 0.02"),
        ("run:clutter", {"mask_padding_px": 1e9}, "mask_padding_px", "<= 200"),
        ("run:clutter", {"threads": 1e6}, "threads", "<= 256"),
        ("run:clutter", {"min_track_frames": 1e12}, "min_track_frames", "<= 1000000"),
        ("run:clutter", {"max_range": 1e308}, "max_range", "<= 1000"),
        ("run:clutter", {"ground_cell": 1e-4}, "ground_cell", ">= 0.02"),
        ("run:clutter", {"dufomap_resolution": math.nan}, "dufomap_resolution", "finite"),
        ("run:clutter", {"voxel_dedup": math.inf}, "voxel_dedup", "finite"),
        ("run:guardrail", {"spacing": 1e-6}, "spacing", ">= 0.02"),
        ("run:guardrail", {"join_gap": math.inf}, "join_gap", "finite"),
        ("guardrail:rebuild", {"min_guardrail_length": 1e308}, "min_guardrail_length", "<= 1000"),
        ("run:phantom", {"model_id": 2**70}, "model_id", "<= 9223372036854775807"),
        ("train:phantom", {"per_class": 1e9}, "per_class", "<= 1000000"),
        ("train:phantom", {"time_limit": math.inf}, "time_limit", "finite"),
        ("train:guardrail", {"block_size": 1e308}, "block_size", "<= 1000"),
        ("import:survey", {"path": "x", "name": "n" * 300}, "name", "at most 255"),
    ],
)
def test_config_values_out_of_physical_bounds_are_422(
    sample_server: Server, admin: httpx.Client, kind: str, config: dict, field: str, problem: str
) -> None:
    body = {"kind": kind, "survey_id": sample_survey_id(sample_server), "config": config}
    if kind.startswith("train:") or kind.startswith("import:"):
        body.pop("survey_id")
    before = len(admin.get("/jobs").json())
    response = admin.post(
        "/jobs",
        content=json.dumps(body, allow_nan=True),  # NaN / Infinity as a sloppy client sends
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert detail.startswith(f"config.{field}:") and "\n" not in detail, detail
    words = {">=": "greater than or equal to", "<=": "less than or equal to"}
    operator, _, number = problem.partition(" ")
    assert (f"{words[operator]} {number}" if operator in words else problem) in detail, detail
    assert len(admin.get("/jobs").json()) == before


def test_roles(sample_server: Server, admin: httpx.Client) -> None:
    survey_id = sample_survey_id(sample_server)
    annotator = sample_server.add_user("jobs-annotator", "annotator")
    other = sample_server.add_user("jobs-other", "annotator")
    refused = annotator.post("/jobs", json={"kind": "train:phantom"})
    assert refused.status_code == 403 and "admin" in refused.json()["detail"]
    mine = annotator.post("/jobs", json={"kind": "run:phantom", "survey_id": survey_id})
    assert mine.status_code == 201 and mine.json()["created_by"] != 1
    job_id = mine.json()["id"]
    assert other.post(f"/jobs/{job_id}/cancel").status_code == 403  # not theirs
    assert other.get(f"/jobs/{job_id}").status_code == 200  # anyone may watch
    assert annotator.post(f"/jobs/{job_id}/cancel").status_code == 200
    job, _ = watch(annotator, job_id)
    assert job["status"] == "cancelled"
    assert annotator.post(f"/jobs/{job_id}/resume").status_code == 200  # own job
    assert admin.post(f"/jobs/{job_id}/cancel").status_code == 200  # admins control any job
    assert watch(admin, job_id)[0]["status"] == "cancelled"
    annotator.close()
    other.close()


def test_a_phantom_job_runs_its_tiles_on_the_servers_cluster(
    sample_server: Server, admin: httpx.Client
) -> None:
    """20 m tiles of the 58 m sample (3), evened over the server's 2 tile workers (2 of 29 m):
    the tiles go to the pool's local Dask cluster, progress says tiles done / tiles, and the
    result's files are assembled from them."""
    survey_id = sample_survey_id(sample_server)
    created = admin.post(
        "/jobs", json={"kind": "run:phantom", "survey_id": survey_id, "config": {"tile_length": 20}}
    )
    assert created.status_code == 201, created.text
    job, seen = watch(admin, created.json()["id"])
    assert job["status"] == "succeeded", job["message"]
    assert seen == sorted(seen)
    log = admin.get(f"/jobs/{job['id']}/log").text
    assert "2 tiles of 29 m: 2 run, 0 kept from an earlier attempt" in log
    report = admin.get(f"/jobs/{job['id']}/files/report.json").json()
    assert report["tiles"]["count"] == 2 and report["counts"]["phantom_points"] > 1000
    too_long = admin.post(
        "/jobs", json={"kind": "run:phantom", "survey_id": survey_id, "config": {"tile_length": 5}}
    )
    assert too_long.status_code == 422 and "config.tile_length" in too_long.text
