"""Guardrail review through a real server: slices uncertain first, batch labels with versions,
the next uncertain slice, the correction preview, model decisions, mesh downloads and the
errors (synthetic sample survey; the guardrail run is ingested by calling the job's task on
the server's database, as a worker would)."""

from __future__ import annotations

import io
import json
import logging
import sqlite3
import time
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
import numpy as np
import pytest
import trimesh
from sqlmodel import Session

from app.core.settings import Settings
from app.jobs.guardrail_tasks import run_guardrail
from app.jobs.registry import JobContext
from app.store.db import make_engine
from app.store.models import Job, JobStatus
from tests.api.server import Server

BASE = "/surveys/1/guardrails"


@dataclass
class Review:
    server: Server
    admin: httpx.Client
    annotator: httpx.Client
    reviewer: httpx.Client
    run: dict

    def db(self) -> sqlite3.Connection:
        return sqlite3.connect(self.server.data_dir / "mmsclean.sqlite3")


@pytest.fixture(scope="module")
def review(sample_server: Server) -> Iterator[Review]:
    """The sample survey with one guardrail run ingested (geometry head: a few seconds)."""
    settings = Settings(data_dir=sample_server.data_dir, sample_dir=None)
    engine = make_engine(f"sqlite:///{sample_server.data_dir / 'mmsclean.sqlite3'}")
    with Session(engine) as session:
        # claimed by this test (running), so that the server's workers leave it alone
        job = Job(
            kind="run:guardrail", survey_id=1, config={"head": "geometry"}, status=JobStatus.running
        )
        session.add(job)
        session.commit()
        job_id = job.id
    workdir = settings.jobs_dir / str(job_id)
    workdir.mkdir(parents=True)
    context = JobContext(
        job_id=job_id, survey_id=1, user_id=None, engine=engine, settings=settings,
        workdir=workdir, log=logging.getLogger("test-guardrail-api"),
        report_progress=lambda fraction, message: False,
    )  # fmt: skip
    result = run_guardrail(context, {"head": "geometry"})
    with Session(engine) as session:
        job = session.get(Job, job_id)
        job.status, job.progress, job.result = JobStatus.succeeded, 1.0, result
        session.commit()
    engine.dispose()
    clients = (
        sample_server.client(),
        sample_server.add_user("gr-annotator", "annotator"),
        sample_server.add_user("gr-reviewer", "reviewer"),
    )
    yield Review(sample_server, *clients, result)
    for client in clients:
        client.close()


def _all_slices(client: httpx.Client, **params) -> list[dict]:
    response = client.get(f"{BASE}/slices", params={"limit": 5000, **params})
    assert response.status_code == 200, response.text
    return response.json()["items"]


def test_slices_uncertain_first_and_paginated(review: Review) -> None:
    c = review.annotator
    everything = _all_slices(c)
    assert len(everything) == review.run["counts"]["slices"] > 100
    along = [(s["component_id"], s["slice_index"]) for s in everything]
    assert along == sorted(along)
    first = c.get(f"{BASE}/slices", params={"uncertain_first": True, "limit": 50}).json()
    second = c.get(
        f"{BASE}/slices", params={"uncertain_first": True, "limit": 50, "offset": 50}
    ).json()
    assert first["total"] == len(everything) and len(first["items"]) == 50
    margin = [abs(s["probability"] - 0.5) for s in first["items"] + second["items"]]
    assert margin == sorted(margin)
    assert min(abs(s["probability"] - 0.5) for s in everything) == margin[0]
    assert not {s["id"] for s in first["items"]} & {s["id"] for s in second["items"]}
    rails = _all_slices(c, label=1)
    assert rails and all(s["label"] == 1 for s in rails)
    assert len(rails) == review.run["counts"]["guardrail_slices"]


def test_put_labels_then_a_stale_version_is_409_with_current(review: Review) -> None:
    c = review.annotator
    me = c.get("/auth/me").json()
    picked = _all_slices(c, labelled=False)[:3]
    body = {"slices": [{"id": s["id"], "version": s["version"], "label": 1} for s in picked]}
    response = c.put(f"{BASE}/slices", json=body)
    assert response.status_code == 200, response.text
    written = response.json()
    assert [s["id"] for s in written] == [s["id"] for s in picked]
    assert all(s["label"] == 1 and s["version"] == p["version"] + 1 for s, p in zip(
        written, picked, strict=True))  # fmt: skip
    assert all(s["labelled_by"] == me["id"] for s in written)
    # the same versions again: someone else's write won; nothing of this batch is written
    fresh = _all_slices(c, labelled=False)[0]
    stale = {
        "slices": [
            {"id": fresh["id"], "version": fresh["version"], "label": 1 - fresh["label"]},
            *({"id": s["id"], "version": s["version"], "label": 0} for s in picked),
        ]
    }
    response = c.put(f"{BASE}/slices", json=stale)
    assert response.status_code == 409, response.text
    current = response.json()["current"]
    assert {s["id"] for s in current} == {s["id"] for s in picked}
    assert all(s["version"] == p["version"] + 1 and s["label"] == 1 for s, p in zip(
        sorted(current, key=lambda s: s["id"]), sorted(picked, key=lambda s: s["id"]),
        strict=True))  # fmt: skip
    again = next(s for s in _all_slices(c) if s["id"] == fresh["id"])
    assert again["version"] == fresh["version"] and again["labelled_by"] is None
    # each label write is audited in its transaction
    with review.db() as db:
        audited = db.execute(
            "SELECT COUNT(*) FROM audit_event WHERE action = 'guardrail_slice.label'"
        ).fetchone()[0]
    assert audited >= 3


def test_label_errors(review: Review) -> None:
    c = review.annotator
    s = _all_slices(c)[0]
    bad = c.put(f"{BASE}/slices", json={"slices": [{"id": s["id"], "version": 1, "label": 2}]})
    assert bad.status_code == 422 and "slices[0].label" in bad.json()["detail"]
    twice = {"slices": [{"id": s["id"], "version": s["version"], "label": 1}] * 2}
    response = c.put(f"{BASE}/slices", json=twice)
    assert response.status_code == 422 and "slices" in response.json()["detail"]
    missing = c.put(f"{BASE}/slices", json={"slices": [{"id": 10**9, "version": 1, "label": 1}]})
    assert missing.status_code == 404 and str(10**9) in missing.json()["detail"]
    other = c.put(
        "/surveys/999/guardrails/slices",
        json={"slices": [{"id": s["id"], "version": 1, "label": 1}]},
    )
    assert other.status_code == 404 and "survey 999" in other.json()["detail"]
    assert c.get("/surveys/999/guardrails/slices").status_code == 404


def test_next_uncertain_slice_with_a_position(review: Review) -> None:
    c = review.annotator
    response = c.get(f"{BASE}/slices/next-uncertain")
    assert response.status_code == 200, response.text
    nxt = response.json()
    unlabelled = _all_slices(c, labelled=False)
    assert nxt["remaining"] == len(unlabelled)
    best = min(abs(s["probability"] - 0.5) for s in unlabelled)
    assert nxt["slice"]["labelled_by"] is None
    assert abs(nxt["slice"]["probability"] - 0.5) == best
    # the position is on the slice: within a few metres of the trajectory at its station
    position = np.array(nxt["position"])
    assert position.shape == (3,) and np.isfinite(position).all()
    with review.db() as db:
        poses = np.array(
            [
                np.array(json.loads(p), dtype=float).reshape(4, 4)[:3, 3]
                for (p,) in db.execute(
                    "SELECT pose FROM frame WHERE survey_id = 1 ORDER BY frame_index"
                )
            ]
        )
    assert np.linalg.norm(poses[:, :2] - position[:2], axis=1).min() < 15.0
    label = {"id": nxt["slice"]["id"], "version": nxt["slice"]["version"], "label": 0}
    assert c.put(f"{BASE}/slices", json={"slices": [label]}).status_code == 200
    after = c.get(f"{BASE}/slices/next-uncertain").json()
    assert after["slice"]["id"] != nxt["slice"]["id"]
    assert after["remaining"] == nxt["remaining"] - 1


def test_preview_correction_does_not_save(review: Review) -> None:
    c = review.annotator
    rails = _all_slices(c, label=1, labelled=False)
    middle = rails[len(rails) // 3]
    body = {"labels": [{"id": middle["id"], "label": 0}]}
    response = c.post(f"{BASE}/slices/preview-correction", json=body)
    assert response.status_code == 200, response.text
    preview = response.json()
    entry = next(s for s in preview["slices"] if s["id"] == middle["id"])
    assert entry["proposed"] == 0 and entry["label"] == 1
    assert entry["corrected_label"] in (0, 1)
    assert preview["max_gap"] == 2 and preview["max_isolated"] == 1
    # with no gap filling a lone "other" inside a rail stays "other"
    strict = c.post(
        f"{BASE}/slices/preview-correction", json={**body, "max_gap": 0, "max_isolated": 0}
    ).json()
    assert next(s for s in strict["slices"] if s["id"] == middle["id"])["corrected_label"] == 0
    still = next(s for s in _all_slices(c) if s["id"] == middle["id"])
    assert still["version"] == middle["version"] and still["label"] == 1
    missing = c.post(
        f"{BASE}/slices/preview-correction", json={"labels": [{"id": 10**9, "label": 1}]}
    )
    assert missing.status_code == 404


def test_models_decisions_and_roles(review: Review) -> None:
    response = review.annotator.get(f"{BASE}/models")
    assert response.status_code == 200, response.text
    models = response.json()
    # the sample's two rails, modelled (the pipe rail's kind is not asserted: 24 m of it, in
    # one run, is too short to tell reliably)
    assert len(models) >= 2 and {m["kind"] for m in models} <= {"beam", "pipe"}
    assert all(m["status"] == "pending" and m["formats"] == ["glb", "obj", "ply"] for m in models)
    assert all(m["params"] is None and m["pole_count"] >= 2 for m in models)
    full = review.annotator.get(f"{BASE}/models", params={"params": True}).json()
    assert all(m["params"]["kind"] == m["kind"] for m in full)
    first, second = models[0], models[1]
    decision = f"{BASE}/models/{first['id']}/decision"
    body = {"version": first["version"], "status": "approved"}
    forbidden = review.annotator.post(decision, json=body)
    assert forbidden.status_code == 403, forbidden.text
    approved = review.reviewer.post(decision, json=body)
    assert approved.status_code == 200, approved.text
    assert approved.json()["status"] == "approved" and approved.json()["decided_by"] is not None
    assert approved.json()["version"] == first["version"] + 1
    stale = review.reviewer.post(decision, json={**body, "status": "rejected"})
    assert stale.status_code == 409
    assert stale.json()["current"]["status"] == "approved"
    assert stale.json()["current"]["version"] == first["version"] + 1
    rejected = review.admin.post(
        f"{BASE}/models/{second['id']}/decision",
        json={"version": second["version"], "status": "rejected"},
    )
    assert rejected.status_code == 200 and rejected.json()["status"] == "rejected"
    bad = review.reviewer.post(decision, json={"version": 2, "status": "pending"})
    assert bad.status_code == 422 and "status" in bad.json()["detail"]
    assert review.reviewer.post(f"{BASE}/models/999999/decision", json=body).status_code == 404
    elsewhere = review.reviewer.post(
        f"/surveys/999/guardrails/models/{first['id']}/decision", json=body
    )
    assert elsewhere.status_code == 404
    with review.db() as db:
        actions = {a for (a,) in db.execute("SELECT action FROM audit_event")}
    assert {"guardrail_model.approve", "guardrail_model.reject"} <= actions


def test_mesh_download(review: Review) -> None:
    c = review.annotator
    model = c.get(f"{BASE}/models").json()[0]
    url = f"{BASE}/models/{model['id']}/mesh"
    for fmt in ("glb", "obj", "ply"):
        response = c.get(url, params={"format": fmt})
        assert response.status_code == 200, response.text
        assert f".{fmt}" in response.headers["content-disposition"]
        mesh = trimesh.load(io.BytesIO(response.content), file_type=fmt, force="mesh")
        assert len(mesh.faces) > 0
    assert c.get(url, params={"format": "stl"}).status_code == 422
    assert c.get(f"{BASE}/models/999999/mesh").status_code == 404
    assert c.get(f"/surveys/999/guardrails/models/{model['id']}/mesh").status_code == 404


def test_rebuild_is_for_reviewers(review: Review) -> None:
    forbidden = review.annotator.post(f"{BASE}/rebuild")
    assert forbidden.status_code == 403
    response = review.reviewer.post(f"{BASE}/rebuild", json={"join_gap": 1.5})
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["kind"] == "guardrail:rebuild"
    with review.db() as db:
        row = db.execute("SELECT kind, survey_id, config FROM job WHERE id = ?", (job["job_id"],))
        kind, survey_id, config = row.fetchone()
    assert (kind, survey_id) == ("guardrail:rebuild", 1) and "join_gap" in config
    bad = review.reviewer.post(f"{BASE}/rebuild", json={"join_gap": -1})
    assert bad.status_code == 422 and "join_gap" in bad.json()["detail"]
    assert review.reviewer.post("/surveys/999/guardrails/rebuild").status_code == 404
    # the server's workers run it: decided models whose slices did not change keep their
    # decision, every other model is rebuilt and pending
    deadline = time.monotonic() + 300
    status = "queued"
    while status in ("queued", "running") and time.monotonic() < deadline:
        time.sleep(0.5)
        with review.db() as db:
            status, result, message = db.execute(
                "SELECT status, result, message FROM job WHERE id = ?", (job["job_id"],)
            ).fetchone()
    assert status == "succeeded", (status, message)
    counts = json.loads(result)["counts"]
    models = review.reviewer.get(f"{BASE}/models").json()
    assert len(models) == counts["models"] == counts["kept"] + counts["new"] > 0
    assert sum(m["status"] != "pending" for m in models) == counts["kept"]
    with review.db() as db:
        events = db.execute("SELECT COUNT(*) FROM audit_event WHERE action = 'guardrail.rebuild'")
        assert events.fetchone()[0] == 1
