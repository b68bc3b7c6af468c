"""Surveys over a real server: import confined to the import root, streamed uploads (LAZ, zip of
a simulated drive) under a size limit, safe unzipping, delete with the uploaded files; the
sensor kind declared at import (route, upload, `import:survey` job) or told by the reader, and
changed later with `PATCH /surveys/{id}` (audited)."""

from __future__ import annotations

import io
import os
import shutil
import sqlite3
import stat
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from sqlmodel import Session, col, select

from app.io.las import write_laz
from app.simulate.survey import SimulationConfig, simulate
from app.store.db import make_engine
from app.store.models import AuditEvent, Frame
from tests.api.server import Server

SAMPLE = Path(__file__).resolve().parents[2] / "data_samples" / "urban-60m"


@pytest.fixture(scope="module")
def sim_dir(server: Server) -> Path:
    """A five-frame simulated drive inside the server's data dir (= its import root)."""
    out = server.data_dir / "incoming" / "sim-street"
    simulate(SimulationConfig(length=6, camera=False, compressed=True), out, True, None)
    return out


@pytest.fixture(scope="module")
def profile_dir(server: Server) -> Path:
    """The shipped sample survey (a profile-scanner simulation) copied into the import root."""
    out = server.data_dir / "incoming" / "urban-60m"
    shutil.copytree(SAMPLE, out)
    return out


@pytest.fixture(scope="module")
def admin(server: Server) -> Iterator[httpx.Client]:
    with server.client() as client:
        yield client


@pytest.fixture(scope="module")
def annotator(server: Server) -> Iterator[httpx.Client]:
    with server.add_user("ann", "annotator") as client:
        yield client


@pytest.fixture(scope="module")
def reviewer(server: Server) -> Iterator[httpx.Client]:
    with server.add_user("rev", "reviewer") as client:
        yield client


def survey_audit(server: Server, entity_id: int) -> list[AuditEvent]:
    """The audit events of one survey, oldest first."""
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    with Session(engine) as session:
        rows = session.exec(
            select(AuditEvent)
            .where(AuditEvent.entity == "survey", AuditEvent.entity_id == str(entity_id))
            .order_by(col(AuditEvent.id))
        ).all()
    engine.dispose()
    return list(rows)


def audit_actions(server: Server, entity_id: int) -> list[str]:
    return [event.action for event in survey_audit(server, entity_id)]


def laz_bytes(tmp_path: Path, n: int = 500) -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 20, (n, 3)) + [500_000.5, 5_400_000.25, 100.0]
    path = write_laz(tmp_path / "map.laz", xyz)
    return path.read_bytes(), xyz


def zip_of(folder: Path, top: str) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                zf.write(path, f"{top}/{path.relative_to(folder)}")
    return buffer.getvalue()


def uploads(server: Server) -> list[Path]:
    folder = server.data_dir / "surveys"
    return sorted(folder.iterdir()) if folder.is_dir() else []


def test_import_detects_and_registers(
    server: Server, sim_dir: Path, annotator: httpx.Client
) -> None:
    response = annotator.post("/surveys/import", json={"path": "incoming/sim-street"})
    assert response.status_code == 201, response.text
    survey = response.json()
    assert survey["format"] == "sim" and survey["frame_count"] == 5
    assert survey["source_path"] == str(sim_dir.resolve())
    assert survey["has_reference_labels"] and survey["point_count"] > 100_000

    listed = annotator.get("/surveys").json()
    assert [s["id"] for s in listed] == [survey["id"]]
    detail = annotator.get(f"/surveys/{survey['id']}").json()
    assert detail["frames"]["count"] == 5
    assert detail["frames"]["points"] == survey["point_count"]
    assert 3.0 < detail["frames"]["trajectory_length_m"] < 8.0  # 6 m street, 5 frames
    assert detail["latest_jobs"] == {}
    assert detail["pillar_labels"]["human"] == [0, 0, 0, 0]
    assert audit_actions(server, survey["id"]) == ["survey.import"]

    named = annotator.post(
        "/surveys/import",
        json={"path": str(sim_dir), "format": "kitti-raw", "name": "as kitti"},
    )
    assert named.status_code == 201, named.text
    assert named.json()["format"] == "kitti-raw" and named.json()["name"] == "as kitti"
    assert not named.json()["has_reference_labels"]


def test_import_refuses_paths_outside_the_root(
    server: Server, sim_dir: Path, annotator: httpx.Client, tmp_path: Path
) -> None:
    outside = tmp_path / "elsewhere"
    shutil.copytree(sim_dir, outside)
    link = server.data_dir / "incoming" / "link-out"
    link.symlink_to(outside, target_is_directory=True)
    sneaky = server.data_dir / "incoming" / "sneaky"
    shutil.copytree(sim_dir, sneaky, ignore=shutil.ignore_patterns("0000000003.laz"))
    (sneaky / "velodyne_points" / "data" / "0000000003.laz").symlink_to(
        outside / "velodyne_points" / "data" / "0000000003.laz"
    )
    for path in ("../..", "../../elsewhere", str(outside), "/etc", "incoming/link-out"):
        response = annotator.post("/surveys/import", json={"path": path})
        assert response.status_code == 400, (path, response.text)
        assert response.json()["detail"].startswith(f"{path}: outside the allowed import root")
    response = annotator.post("/surveys/import", json={"path": "incoming/sneaky"})
    assert response.status_code == 400
    assert "0000000003.laz: outside the allowed import root" in response.json()["detail"]


def test_the_import_root_is_named_to_those_who_import(
    server: Server, annotator: httpx.Client
) -> None:
    """The import form names the folder, not only the variable that sets it (issue 20)."""
    answer = annotator.get("/surveys/import-root")
    assert answer.status_code == 200, answer.text
    assert answer.json() == {"path": str(server.data_dir.resolve())}
    assert httpx.get(f"{server.url}/surveys/import-root").status_code == 401


def test_import_missing_or_bad_data_is_422(
    server: Server, annotator: httpx.Client, admin: httpx.Client
) -> None:
    before = len(admin.get("/surveys").json())
    response = annotator.post("/surveys/import", json={"path": "incoming/nothing-here"})
    assert response.status_code == 422
    assert response.json()["detail"] == "incoming/nothing-here: does not exist"

    junk = server.data_dir / "incoming" / "junk"
    junk.mkdir()
    (junk / "readme.txt").write_text("not a survey")
    response = annotator.post("/surveys/import", json={"path": "incoming/junk"})
    assert response.status_code == 422
    assert "junk: cannot tell the format" in response.json()["detail"]

    (junk / "broken.laz").write_bytes(b"LASF" + b"\0" * 50)
    response = annotator.post("/surveys/import", json={"path": "incoming/junk/broken.laz"})
    assert response.status_code == 422
    assert "broken.laz" in response.json()["detail"]

    response = annotator.post(
        "/surveys/import", json={"path": "incoming/junk", "format": "nonsense"}
    )
    assert response.status_code == 422 and "nonsense" in response.json()["detail"]
    assert len(admin.get("/surveys").json()) == before


def test_upload_laz(server: Server, annotator: httpx.Client, tmp_path: Path) -> None:
    data, xyz = laz_bytes(tmp_path)
    response = annotator.post("/surveys/upload", params={"filename": "street.laz"}, content=data)
    assert response.status_code == 201, response.text
    survey = response.json()
    assert survey["format"] == "las" and survey["name"] == "street"
    assert survey["frame_count"] == 1 and survey["point_count"] == len(xyz)
    assert survey["origin"] == [500_000.0, 5_400_000.0, 100.0]
    stored = Path(survey["source_path"])
    assert stored.parent.parent == (server.data_dir / "surveys").resolve()
    assert stored.read_bytes() == data
    assert audit_actions(server, survey["id"]) == ["survey.upload"]


def test_upload_zip_of_a_simulated_drive(
    server: Server, sim_dir: Path, annotator: httpx.Client
) -> None:
    response = annotator.post(
        "/surveys/upload",
        params={"filename": "drive.zip", "name": "zipped drive"},
        content=zip_of(sim_dir, "sim-street"),
    )
    assert response.status_code == 201, response.text
    survey = response.json()
    assert survey["format"] == "sim" and survey["frame_count"] == 5
    source = Path(survey["source_path"])
    assert source.name == "sim-street" and (source / "ground_truth" / "simulation.json").is_file()
    assert not (source.parent.parent / ".upload.zip").exists()  # the archive is unpacked, gone


def evil_zip(member: str, symlink: bool = False) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        zf.writestr("drive/readme.txt", "fine")
        info = zipfile.ZipInfo(member)
        if symlink:
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
        zf.writestr(info, "/etc/passwd" if symlink else "gotcha")
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("member", "symlink", "problem"),
    [
        ("../escape.txt", False, "points outside the archive's folder"),
        ("drive/../../escape.txt", False, "points outside the archive's folder"),
        ("/abs/escape.txt", False, "points outside the archive's folder"),
        ("drive/link", True, "is a symbolic link; links are refused"),
    ],
)
def test_upload_zip_refuses_escaping_members(
    server: Server, annotator: httpx.Client, member: str, symlink: bool, problem: str
) -> None:
    before = uploads(server)
    response = annotator.post(
        "/surveys/upload", params={"filename": "evil.zip"}, content=evil_zip(member, symlink)
    )
    assert response.status_code == 422, response.text
    assert response.json()["detail"] == f"evil.zip: zip member {member!r} {problem}"
    assert uploads(server) == before
    assert not (server.data_dir / "escape.txt").exists()
    assert not (server.data_dir / "surveys" / "escape.txt").exists()


def test_upload_bad_files_are_422_and_leave_nothing(
    server: Server, annotator: httpx.Client
) -> None:
    before = uploads(server)
    response = annotator.post(
        "/surveys/upload", params={"filename": "bad.laz"}, content=b"LASF" + b"x" * 300
    )
    assert response.status_code == 422
    assert response.json()["detail"].startswith("bad.laz: not a LAS/LAZ file")
    truncated = io.BytesIO()
    with zipfile.ZipFile(truncated, "w") as zf:
        zf.writestr("drive/velodyne_points/data/0000000000.bin", b"abc")
    response = annotator.post(
        "/surveys/upload", params={"filename": "d.zip"}, content=truncated.getvalue()
    )
    assert response.status_code == 422
    assert response.json()["detail"].startswith(
        "d.zip/drive/velodyne_points/data/0000000000.bin: truncated"
    )
    response = annotator.post(
        "/surveys/upload", params={"filename": "notzip.zip"}, content=b"plain text"
    )
    assert response.status_code == 422
    assert response.json()["detail"].startswith("notzip.zip: is not a readable zip archive")
    for name in ("../x.laz", "x.exe", ".hidden.laz"):
        response = annotator.post("/surveys/upload", params={"filename": name}, content=b"x")
        assert response.status_code == 422
        assert response.json()["detail"].startswith("filename:")
    response = annotator.post("/surveys/upload", params={"filename": "empty.laz"}, content=b"")
    assert response.status_code == 422 and "empty" in response.json()["detail"]
    assert uploads(server) == before


def test_uploads_over_the_limit_are_413(tmp_path: Path) -> None:
    small = Server(
        tmp_path / "var",
        env={"MMSCLEAN_SAMPLE_DIR": "", "MMSCLEAN_MAX_UPLOAD_MB": "0.05"},  # 52,428 bytes
    ).start()
    try:
        with small.client() as client:
            body = os.urandom(200_000)

            def chunks() -> Iterator[bytes]:  # no Content-Length: the limit hits mid-stream
                for start in range(0, len(body), 8192):
                    yield body[start : start + 8192]

            response = client.post(
                "/surveys/upload", params={"filename": "big.laz"}, content=chunks()
            )
            assert response.status_code == 413, response.text
            assert response.json()["detail"] == "big.laz: larger than the upload limit of 0.05 MB"
            response = client.post("/surveys/upload", params={"filename": "big.laz"}, content=body)
            assert response.status_code == 413  # refused on Content-Length alone

            bomb = io.BytesIO()
            with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zf:
                zf.writestr("drive/zeros.bin", bytes(5_000_000))
            assert len(bomb.getvalue()) < 20_000
            response = client.post(
                "/surveys/upload", params={"filename": "bomb.zip"}, content=bomb.getvalue()
            )
            assert response.status_code == 413
            assert response.json()["detail"].startswith("bomb.zip (unpacked): larger than")
            assert client.get("/surveys").json() == []
        surveys = small.data_dir / "surveys"
        assert not surveys.exists() or list(surveys.iterdir()) == []  # partial files deleted
    finally:
        small.stop()


def test_delete(
    server: Server,
    sim_dir: Path,
    annotator: httpx.Client,
    reviewer: httpx.Client,
    tmp_path: Path,
) -> None:
    data, _ = laz_bytes(tmp_path)
    uploaded = annotator.post("/surveys/upload", params={"filename": "gone.laz"}, content=data)
    assert uploaded.status_code == 201
    survey_id = uploaded.json()["id"]
    folder = Path(uploaded.json()["source_path"]).parent
    imported = annotator.post("/surveys/import", json={"path": str(sim_dir)}).json()

    response = annotator.delete(f"/surveys/{survey_id}")
    assert response.status_code == 403
    assert reviewer.delete(f"/surveys/{survey_id}").status_code == 204
    assert not folder.exists()
    assert reviewer.get(f"/surveys/{survey_id}").status_code == 404
    assert reviewer.delete(f"/surveys/{survey_id}").status_code == 404
    assert audit_actions(server, survey_id) == ["survey.upload", "survey.delete"]

    assert reviewer.delete(f"/surveys/{imported['id']}").status_code == 204
    assert (sim_dir / "ground_truth" / "simulation.json").is_file()  # imported files stay
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    with Session(engine) as session:
        frames = session.exec(select(Frame).where(Frame.survey_id == imported["id"])).all()
    engine.dispose()
    assert frames == []  # cascaded

    # the next survey does not get the deleted newest one's id (nor its history)
    again = annotator.post("/surveys/upload", params={"filename": "new.laz"}, content=data)
    assert again.json()["id"] > imported["id"]
    assert audit_actions(server, again.json()["id"]) == ["survey.upload"]
    assert reviewer.delete(f"/surveys/{again.json()['id']}").status_code == 204


def test_needs_login(server: Server) -> None:
    assert httpx.get(f"{server.url}/surveys").status_code == 401
    response = httpx.post(f"{server.url}/surveys/import", json={"path": "x"})
    assert response.status_code == 401


def test_import_as_a_job(server: Server, sim_dir: Path, annotator: httpx.Client) -> None:
    """`import:survey` through /jobs: the path is checked when queued (400 / 422 at once), the
    worker registers the survey (audited with the job), a folder with nothing readable fails
    the job with the reader's message."""
    body = {"kind": "import:survey", "config": {"path": "incoming/sim-street", "name": "by job"}}
    queued = annotator.post("/jobs", json=body)
    assert queued.status_code == 201, queued.text
    job = wait_job_done(annotator, queued.json()["id"])
    assert job["status"] == "succeeded", job
    survey = annotator.get(f"/surveys/{job['result']['survey_id']}").json()
    assert survey["name"] == "by job" and survey["frame_count"] == 5
    assert job["result"] == {"survey_id": survey["id"], "name": "by job", "frames": 5}
    assert audit_actions(server, survey["id"])[-1] == "survey.import"

    outside = annotator.post("/jobs", json={"kind": "import:survey", "config": {"path": "/etc"}})
    assert outside.status_code == 400
    assert outside.json()["detail"].startswith("/etc: outside the allowed import root")
    for config, field in (({}, "config.path"), ({"path": "x", "speed": 1}, "config.speed")):
        refused = annotator.post("/jobs", json={"kind": "import:survey", "config": config})
        assert refused.status_code == 422 and refused.json()["detail"].startswith(field)

    empty = server.data_dir / "incoming" / "empty-drive"
    (empty / "velodyne_points" / "data").mkdir(parents=True)
    failing = {"kind": "import:survey", "config": {"path": str(empty), "format": "kitti-raw"}}
    job = wait_job_done(annotator, annotator.post("/jobs", json=failing).json()["id"])
    assert job["status"] == "failed" and "empty-drive" in job["message"]


def wait_job_done(client: httpx.Client, job_id: int, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["status"] in ("succeeded", "failed", "cancelled", "interrupted"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} still not finished after {timeout} s")


# --- the sensor kind --------------------------------------------------------------------------


def sensor_events(server: Server, survey_id: int) -> list[AuditEvent]:
    return [e for e in survey_audit(server, survey_id) if e.action == "survey.sensor"]


def test_import_tells_the_kind_by_the_reader(
    sim_dir: Path, profile_dir: Path, annotator: httpx.Client
) -> None:
    profile = annotator.post("/surveys/import", json={"path": "incoming/urban-60m"})
    assert profile.status_code == 201, profile.text
    assert profile.json()["sensor_kind"] == "profile"
    assert profile.json()["sensor_note"] == "sim reader: scanner profile"
    rotating = annotator.post("/surveys/import", json={"path": "incoming/sim-street"}).json()
    assert rotating["sensor_kind"] == "rotating"
    assert rotating["sensor_note"] == "sim reader: scanner hdl64"
    listed = {s["id"]: s for s in annotator.get("/surveys").json()}
    assert listed[profile.json()["id"]]["sensor_kind"] == "profile"
    detail = annotator.get(f"/surveys/{rotating['id']}").json()
    assert (detail["sensor_kind"], detail["sensor_note"]) == ("rotating", rotating["sensor_note"])


def test_import_declares_the_kind(sim_dir: Path, annotator: httpx.Client) -> None:
    body = {"path": "incoming/sim-street", "sensor": "profile"}  # declared wins
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
    assert changed.json()["sensor_note"] == "declared by ann"
    assert changed.json()["name"] == survey["name"]
    detail = annotator.get(f"/surveys/{survey['id']}").json()
    assert (detail["sensor_kind"], detail["sensor_note"]) == ("profile", "declared by ann")
    with server.client() as admin:  # roles nest: an admin may too
        again = admin.patch(f"/surveys/{survey['id']}", json={"sensor_kind": "rotating"})
        assert again.status_code == 200 and again.json()["sensor_note"] == "declared by admin"
        users = {u["username"]: u["id"] for u in admin.get("/users").json()}
    events = sensor_events(server, survey["id"])
    assert [(e.user_id, e.payload) for e in events] == [
        (users["ann"], {"before": "unknown", "after": "profile"}),
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
    config = {"path": "incoming/sim-street", "name": "job profile", "sensor": "profile"}
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
