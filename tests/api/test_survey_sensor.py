"""A survey's sensor kind over a real server: declared at import (the route, the upload, the
`import:survey` job) or told by the reader, changed later with `PATCH /surveys/{id}` (audited),
and shown for model versions."""

from __future__ import annotations

import shutil
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlmodel import Session, col, select

from app.simulate.survey import SimulationConfig, simulate
from app.store.db import make_engine
from app.store.models import AuditEvent
from tests.api.server import Server
from tests.api.test_surveys import laz_bytes, wait_job_done

SAMPLE = Path(__file__).resolve().parents[2] / "data_samples" / "urban-60m"


@pytest.fixture(scope="module")
def sim_dir(server: Server) -> Path:
    """A five-frame drive of the simulator's rotating scanner (HDL-64E) in the import root."""
    out = server.data_dir / "incoming" / "sim-rotating"
    simulate(SimulationConfig(length=6, camera=False, compressed=True), out, True, None)
    return out


@pytest.fixture(scope="module")
def profile_dir(server: Server) -> Path:
    """The shipped sample survey (a profile-scanner simulation) copied into the import root."""
    out = server.data_dir / "incoming" / "urban-60m"
    shutil.copytree(SAMPLE, out)
    return out


@pytest.fixture(scope="module")
def annotator(server: Server) -> Iterator[httpx.Client]:
    with server.add_user("sensor-ann", "annotator") as client:
        yield client


def sensor_events(server: Server, survey_id: int) -> list[AuditEvent]:
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    with Session(engine) as session:
        rows = session.exec(
            select(AuditEvent)
            .where(AuditEvent.entity == "survey", AuditEvent.entity_id == str(survey_id))
            .where(AuditEvent.action == "survey.sensor")
            .order_by(col(AuditEvent.id))
        ).all()
    engine.dispose()
    return list(rows)


def test_import_tells_the_kind_by_the_reader(
    sim_dir: Path, profile_dir: Path, annotator: httpx.Client
) -> None:
    profile = annotator.post("/surveys/import", json={"path": "incoming/urban-60m"})
    assert profile.status_code == 201, profile.text
    assert profile.json()["sensor_kind"] == "profile"
    assert profile.json()["sensor_note"] == "sim reader: scanner profile"
    rotating = annotator.post("/surveys/import", json={"path": "incoming/sim-rotating"}).json()
    assert rotating["sensor_kind"] == "rotating"
    assert rotating["sensor_note"] == "sim reader: scanner hdl64"
    listed = {s["id"]: s for s in annotator.get("/surveys").json()}
    assert listed[profile.json()["id"]]["sensor_kind"] == "profile"
    detail = annotator.get(f"/surveys/{rotating['id']}").json()
    assert (detail["sensor_kind"], detail["sensor_note"]) == ("rotating", rotating["sensor_note"])


def test_import_declares_the_kind(sim_dir: Path, annotator: httpx.Client) -> None:
    body = {"path": "incoming/sim-rotating", "sensor": "profile"}  # declared wins
    declared = annotator.post("/surveys/import", json=body)
    assert declared.status_code == 201, declared.text
    survey = declared.json()
    assert (survey["sensor_kind"], survey["sensor_note"]) == ("profile", "declared at import")
    assert annotator.get(f"/surveys/{survey['id']}").json()["sensor_kind"] == "profile"

    before = len(annotator.get("/surveys").json())
    for bad in ("unknown", "Rotating", "lidar", 3):
        refused = annotator.post("/surveys/import", json={**body, "sensor": bad})
        assert refused.status_code == 422, (bad, refused.text)
        assert refused.json()["detail"].startswith("sensor:"), refused.json()
    assert len(annotator.get("/surveys").json()) == before


def test_upload_with_and_without_a_sensor(annotator: httpx.Client, tmp_path: Path) -> None:
    data, _ = laz_bytes(tmp_path)
    plain = annotator.post("/surveys/upload", params={"filename": "plain.laz"}, content=data)
    assert plain.status_code == 201, plain.text
    assert plain.json()["sensor_kind"] == "unknown"  # a map without point times
    assert plain.json()["sensor_note"]
    params = {"filename": "declared.laz", "sensor": "rotating"}
    declared = annotator.post("/surveys/upload", params=params, content=data)
    assert declared.status_code == 201, declared.text
    assert declared.json()["sensor_kind"] == "rotating"
    assert declared.json()["sensor_note"] == "declared at import"
    params = {"filename": "bad.laz", "sensor": "spinning"}
    refused = annotator.post("/surveys/upload", params=params, content=data)
    assert refused.status_code == 422 and refused.json()["detail"].startswith("sensor:")


def test_patch_declares_the_kind_later(
    server: Server, annotator: httpx.Client, tmp_path: Path
) -> None:
    data, _ = laz_bytes(tmp_path)
    survey = annotator.post("/surveys/upload", params={"filename": "m.laz"}, content=data).json()
    assert survey["sensor_kind"] == "unknown"

    changed = annotator.patch(f"/surveys/{survey['id']}", json={"sensor_kind": "profile"})
    assert changed.status_code == 200, changed.text
    assert changed.json()["sensor_kind"] == "profile"
    assert changed.json()["sensor_note"] == "declared by sensor-ann"
    assert changed.json()["name"] == survey["name"]
    detail = annotator.get(f"/surveys/{survey['id']}").json()
    assert (detail["sensor_kind"], detail["sensor_note"]) == ("profile", "declared by sensor-ann")
    with server.client() as admin:  # roles nest: an admin may too
        again = admin.patch(f"/surveys/{survey['id']}", json={"sensor_kind": "rotating"})
        assert again.status_code == 200 and again.json()["sensor_note"] == "declared by admin"
        users = {u["username"]: u["id"] for u in admin.get("/users").json()}
    events = sensor_events(server, survey["id"])
    assert [(e.user_id, e.payload) for e in events] == [
        (users["sensor-ann"], {"before": "unknown", "after": "profile"}),
        (users["admin"], {"before": "profile", "after": "rotating"}),
    ]

    missing = annotator.patch("/surveys/999999", json={"sensor_kind": "profile"})
    assert missing.status_code == 404
    for body, field in (
        ({"sensor_kind": "unknown"}, "sensor_kind:"),
        ({"sensor_kind": "lidar"}, "sensor_kind:"),
        ({}, "sensor_kind:"),
        ({"sensor_kind": "profile", "name": "renamed"}, "name:"),
    ):
        refused = annotator.patch(f"/surveys/{survey['id']}", json=body)
        assert refused.status_code == 422, (body, refused.text)
        assert refused.json()["detail"].startswith(field), refused.json()
    assert annotator.get(f"/surveys/{survey['id']}").json()["sensor_kind"] == "rotating"
    assert len(sensor_events(server, survey["id"])) == 2
    # no role below annotator exists: without a login it is refused
    anonymous = httpx.patch(f"{server.url}/surveys/{survey['id']}", json={"sensor_kind": "profile"})
    assert anonymous.status_code == 401


def test_import_job_takes_a_sensor(sim_dir: Path, annotator: httpx.Client) -> None:
    config = {"path": "incoming/sim-rotating", "name": "job profile", "sensor": "profile"}
    queued = annotator.post("/jobs", json={"kind": "import:survey", "config": config})
    assert queued.status_code == 201, queued.text
    job = wait_job_done(annotator, queued.json()["id"])
    assert job["status"] == "succeeded", job
    survey = annotator.get(f"/surveys/{job['result']['survey_id']}").json()
    assert (survey["sensor_kind"], survey["sensor_note"]) == ("profile", "declared at import")

    for bad in ("unknown", "lidar", 7, ["profile"]):
        body = {"kind": "import:survey", "config": {**config, "sensor": bad}}
        refused = annotator.post("/jobs", json=body)
        assert refused.status_code == 422, (bad, refused.text)
        assert refused.json()["detail"].startswith("config.sensor:"), refused.json()


def test_model_versions_show_their_kind(server: Server) -> None:
    with sqlite3.connect(server.data_dir / "mmsclean.sqlite3") as conn:
        for name, kind in (("old", None), ("spinning", "rotating")):
            columns = "created_at, updated_at, version, pipeline, name, checkpoint_path, metrics"
            values = "datetime('now'), datetime('now'), 1, 'phantom', ?, '/x.pt', '{}'"
            if kind is not None:
                columns, values = f"{columns}, sensor_kind", f"{values}, '{kind}'"
            conn.execute(
                f"INSERT INTO model_version ({columns}, trained_on, is_promoted)"
                f" VALUES ({values}, '{{}}', 0)",
                (name,),
            )
    with server.client() as admin:
        kinds = {m["name"]: m["sensor_kind"] for m in admin.get("/models").json()}
        assert kinds["old"] == "profile" and kinds["spinning"] == "rotating"
        one = admin.get("/models").json()[0]
        assert admin.get(f"/models/{one['id']}").json()["sensor_kind"] == one["sensor_kind"]
