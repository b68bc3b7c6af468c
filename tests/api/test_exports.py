"""Exports over a real server, with labels, jobs and guardrail models written straight into its
SQLite file: clutter maps, guardrail meshes, the pillar label set, the QA report; 404 when there
is nothing to export, 403 for annotators, every download audited."""

from __future__ import annotations

import base64
import csv
import io
import json
import re
import subprocess
import time
import zipfile
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import cv2
import httpx
import laspy
import numpy as np
import pytest
from laspy.vlrs.known import WktCoordinateSystemVlr
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

from app.io.asprs import CLUTTER_LABEL_TO_ASPRS, REMOVED_CLUTTER_ASPRS, to_asprs
from app.io.las import read_las_points, write_laz
from app.io.pcd import read_pcd
from app.io.semantickitti import read_label_file
from app.io.survey import Frame as SimFrame
from app.io.survey import PointCloud
from app.io.survey import Survey as SimSurvey
from app.metrics.classification import binary_scores, scores_from_confusion
from app.metrics.removal import dynamic_scores, error_matrix
from app.pipelines.clutter.maps import maps_offset, write_frame_maps
from app.pipelines.guardrail.meshes import export_mesh
from app.store.clutter_review import DecisionWrite, decide, list_instances, replace_instances
from app.store.db import make_engine
from app.store.models import (
    AuditEvent,
    ClutterDecision,
    ClutterInstance,
    Decision,
    Frame,
    GuardrailKind,
    GuardrailModel,
    Job,
    JobStatus,
    LabelSource,
    ModelStatus,
    PillarLabel,
    Survey,
)
from app.store.pillar_labels import STORE_GRID
from tests.api.server import Server
from tests.cli import mmsclean

EXPORTS = ("cleaned.laz", "removed.laz", "guardrails.zip", "pillars.csv", "qa-report.html")
MAP_FORMATS = ("classified.laz", "cleaned.pcd", "map.pcd")  # issue 20: what mapping teams read
NEW_EXPORTS = (*MAP_FORMATS, "semantickitti-labels.zip")
WKT = (
    'PROJCS["ETRS89 / UTM zone 32N",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_System_'
    '1989",SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],UNIT["degree",'
    '0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["central_meridian",9],'
    'PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],UNIT["metre",1],'
    'AUTHORITY["EPSG","25832"]]'
)


@pytest.fixture(scope="module")
def engine(server: Server) -> Iterator[Engine]:
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    yield engine
    engine.dispose()


@pytest.fixture(scope="module")
def reviewer(server: Server) -> Iterator[httpx.Client]:
    with server.add_user("rev", "reviewer") as client:
        yield client


@pytest.fixture(scope="module")
def annotator(server: Server) -> Iterator[httpx.Client]:
    with server.add_user("ann", "annotator") as client:
        yield client


@pytest.fixture(scope="module")
def survey_id(server: Server, annotator: httpx.Client) -> int:
    """A one-map survey uploaded as LAZ."""
    path = write_laz(
        server.data_dir / "upload.laz", np.random.default_rng(0).uniform(0, 9, (50, 3))
    )
    response = annotator.post(
        "/surveys/upload", params={"filename": "Main Street.laz"}, content=path.read_bytes()
    )
    assert response.status_code == 201, response.text
    return response.json()["id"]


def user_id(client: httpx.Client, name: str) -> int:
    return next(u["id"] for u in client.get("/users").json() if u["username"] == name)


def exports_audited(engine: Engine, survey_id: int) -> list[str]:
    with Session(engine) as session:
        actions = session.exec(
            select(AuditEvent.action).where(
                AuditEvent.entity_id == str(survey_id), AuditEvent.action.startswith("export.")
            )
        ).all()
    return list(actions)


def add(engine: Engine, *records: object) -> None:
    with Session(engine) as session:
        session.add_all(records)
        session.commit()


def succeeded_job(survey_id: int, kind: str, files: dict, report: Path | None) -> Job:
    now = datetime.now(UTC)
    result: dict = {"files": {k: str(v) for k, v in files.items()}}
    if report is not None:
        result["report"] = str(report)
    return Job(
        survey_id=survey_id,
        kind=kind,
        status=JobStatus.succeeded,
        progress=1.0,
        started_at=now,
        finished_at=now,
        result=result,
    )


def test_nothing_to_export_is_404(survey_id: int, reviewer: httpx.Client) -> None:
    for name in ("cleaned.laz", "removed.laz"):
        response = reviewer.get(f"/surveys/{survey_id}/exports/{name}")
        assert response.status_code == 404
        assert "has no finished clutter or phantom run" in response.json()["detail"]
    response = reviewer.get(f"/surveys/{survey_id}/exports/guardrails.zip")
    assert response.status_code == 404 and "no approved guardrail model" in response.text
    response = reviewer.get(f"/surveys/{survey_id}/exports/pillars.csv")
    assert response.status_code == 404 and "no human pillar labels" in response.text
    for name in (*EXPORTS, *NEW_EXPORTS):
        response = reviewer.get(f"/surveys/9999/exports/{name}")
        assert response.status_code == 404
        assert response.json()["detail"] == "survey 9999 not found"


def test_annotators_cannot_export(survey_id: int, annotator: httpx.Client) -> None:
    for name in (*EXPORTS, *NEW_EXPORTS, "pillars.npz"):
        response = annotator.get(f"/surveys/{survey_id}/exports/{name}")
        assert response.status_code == 403, name
        assert "needs the reviewer role" in response.json()["detail"]


def test_pillars_csv_and_npz(
    survey_id: int, engine: Engine, reviewer: httpx.Client, annotator: httpx.Client
) -> None:
    ann = user_id(reviewer, "ann")
    ix = np.array([-3, 0, 12])
    iy = np.array([7, 0, -1])
    cells = STORE_GRID.cell_id(ix, iy)
    add(
        engine,
        *[
            PillarLabel(
                survey_id=survey_id,
                cell_id=int(c),
                label=lab,
                source=LabelSource.human,
                user_id=ann,
            )
            for c, lab in zip(cells, [3, 0, 1], strict=True)
        ],
        PillarLabel(
            survey_id=survey_id,
            cell_id=int(cells[1]),
            label=2,
            source=LabelSource.model,
            confidence=0.625,
        ),
    )
    response = reviewer.get(f"/surveys/{survey_id}/exports/pillars.csv")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/csv")
    assert (
        response.headers["content-disposition"] == 'attachment; filename="Main-Street-pillars.csv"'
    )
    rows = list(csv.DictReader(io.StringIO(response.text)))
    assert len(rows) == 3
    by_cell = {int(r["cell_id"]): r for r in rows}
    phantom = by_cell[int(cells[0])]
    assert (phantom["ix"], phantom["iy"]) == ("-3", "7")
    assert (float(phantom["x"]), float(phantom["y"])) == (-0.5, 1.5)  # centre of the 0.2 m cell
    assert (phantom["label"], phantom["label_name"], phantom["source"]) == ("3", "phantom", "human")
    assert phantom["user"] == "ann" and phantom["confidence"] == ""
    assert datetime.fromisoformat(phantom["updated_at"]).tzinfo is not None

    with_model = reviewer.get(
        f"/surveys/{survey_id}/exports/pillars.csv", params={"include_model": "true"}
    )
    rows = list(csv.DictReader(io.StringIO(with_model.text)))
    assert len(rows) == 4
    model = next(r for r in rows if r["source"] == "model")
    assert model["label_name"] == "short_object" and float(model["confidence"]) == 0.625

    npz = reviewer.get(
        f"/surveys/{survey_id}/exports/pillars.npz", params={"include_model": "true"}
    )
    assert npz.status_code == 200
    arrays = np.load(io.BytesIO(npz.content))
    assert sorted(arrays["cell_id"].tolist()) == sorted([*cells.tolist(), int(cells[1])])
    assert arrays["cell_size"] == 0.2 and list(arrays["label_names"])[3] == "phantom"
    assert np.isnan(arrays["confidence"][arrays["source"] == "human"]).all()
    assert exports_audited(engine, survey_id) == [
        "export.pillars_csv",
        "export.pillars_csv",
        "export.pillars_npz",
    ]


def test_cleaned_and_removed_maps(
    server: Server, survey_id: int, engine: Engine, reviewer: httpx.Client
) -> None:
    out = server.data_dir / "jobs" / "clutter-old"
    rng = np.random.default_rng(1)
    old = write_laz(out / "cleaned.laz", rng.uniform(0, 5, (20, 3)))
    job_dir = server.data_dir / "jobs" / "clutter-new"
    cleaned = write_laz(job_dir / "cleaned.laz", rng.uniform(0, 5, (40, 3)))
    removed = write_laz(job_dir / "removed.laz", rng.uniform(0, 5, (7, 3)))
    add(engine, succeeded_job(survey_id, "run:clutter", {"cleaned": old, "removed": old}, None))
    add(
        engine,
        succeeded_job(
            survey_id, "clutter:recompute", {"cleaned": cleaned, "removed": removed}, None
        ),
        Job(survey_id=survey_id, kind="run:clutter", status=JobStatus.failed),
    )
    response = reviewer.get(f"/surveys/{survey_id}/exports/cleaned.laz")
    assert response.status_code == 200, response.text
    assert response.content == cleaned.read_bytes()  # the newest succeeded run, not the failed
    assert response.headers["content-type"] == "application/vnd.laszip"
    assert 'filename="Main-Street-clutter-cleaned.laz"' in response.headers["content-disposition"]
    assert response.headers["content-disposition"].startswith("attachment")
    response = reviewer.get(f"/surveys/{survey_id}/exports/removed.laz")
    assert response.content == removed.read_bytes()

    # a phantom run removes points too: its maps are exported, the newest by default and either
    # pipeline's when asked (issue 20: the export waited for a clutter run)
    phantom_dir = server.data_dir / "jobs" / "phantom-new"
    phantom_cleaned = write_laz(phantom_dir / "cleaned.laz", rng.uniform(0, 5, (33, 3)))
    add(engine, succeeded_job(survey_id, "run:phantom", {"cleaned": phantom_cleaned}, None))
    newest = reviewer.get(f"/surveys/{survey_id}/exports/cleaned.laz")
    assert newest.content == phantom_cleaned.read_bytes()
    assert 'filename="Main-Street-phantom-cleaned.laz"' in newest.headers["content-disposition"]
    clutter = reviewer.get(f"/surveys/{survey_id}/exports/cleaned.laz?source=clutter")
    assert clutter.content == cleaned.read_bytes()
    nothing = reviewer.get(f"/surveys/{survey_id}/exports/removed.laz?source=phantom")
    assert nothing.status_code == 404 and "wrote no removed map" in nothing.json()["detail"]
    bad = reviewer.get(f"/surveys/{survey_id}/exports/cleaned.laz?source=guardrail")
    assert bad.status_code == 422 and "source" in bad.json()["detail"]

    removed.unlink()
    response = reviewer.get(f"/surveys/{survey_id}/exports/removed.laz?source=clutter")
    assert response.status_code == 404 and "gone from disk" in response.json()["detail"]
    assert exports_audited(engine, survey_id)[-2:] == ["export.cleaned_laz", "export.cleaned_laz"]


def test_guardrail_meshes(
    server: Server, survey_id: int, engine: Engine, reviewer: httpx.Client
) -> None:
    box = (
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64) + 1000.0,
        np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
    )
    folder = server.data_dir / "jobs" / "guardrail" / "guardrails"
    first = export_mesh(box, folder, "g0")
    second = export_mesh(box, folder, "g1")
    rev = user_id(reviewer, "rev")
    add(
        engine,
        GuardrailModel(
            survey_id=survey_id,
            guardrail_index=0,
            kind=GuardrailKind.pipe,
            mesh_path=first["glb"],
            params={"files": first, "radius": 0.05},
            unit_count=3,
            status=ModelStatus.approved,
            decided_by=rev,
            decided_at=datetime.now(UTC),
        ),
        GuardrailModel(
            survey_id=survey_id,
            guardrail_index=1,
            kind=GuardrailKind.beam,
            mesh_path=second["glb"],
            params={"files": second},
            status=ModelStatus.rejected,
        ),
    )
    for fmt in ("glb", "obj"):
        response = reviewer.get(
            f"/surveys/{survey_id}/exports/guardrails.zip", params={"format": fmt}
        )
        assert response.status_code == 200, response.text
        assert response.headers["content-type"] == "application/zip"
        assert (
            f'filename="Main-Street-guardrails-{fmt}.zip"'
            in response.headers["content-disposition"]
        )
        with zipfile.ZipFile(io.BytesIO(response.content)) as zf:
            mesh = f"Main-Street-guardrail-000-pipe.{fmt}"
            assert sorted(zf.namelist()) == sorted([mesh, "manifest.json"])
            assert zf.read(mesh) == Path(first[fmt]).read_bytes()
            manifest = json.loads(zf.read("manifest.json"))
        assert manifest["models"][0]["approved_by"] == "rev"
        assert manifest["models"][0]["params"] == {"radius": 0.05}
    response = reviewer.get(
        f"/surveys/{survey_id}/exports/guardrails.zip", params={"format": "ply"}
    )
    assert response.status_code == 422
    # the temporary archives are deleted once sent, by a task that runs after the response:
    # give it a moment to run
    exports = server.data_dir / "cache" / "exports"
    deadline = time.monotonic() + 10
    while list(exports.glob("*.zip")) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert list(exports.glob("*.zip")) == []


def write_report(folder: Path, report: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "report.json"
    path.write_text(json.dumps(report))
    return path


def test_qa_report(server: Server, survey_id: int, engine: Engine, reviewer: httpx.Client) -> None:
    reference = np.r_[np.ones(10, bool), np.zeros(90, bool)]
    removed = np.r_[np.ones(8, bool), np.zeros(2, bool), np.ones(3, bool), np.zeros(87, bool)]
    entry = {
        "error_matrix": error_matrix(reference, removed).as_dict(),
        "scores": dynamic_scores(reference, removed).as_dict(),
    }
    clutter_metrics = {"in_view": {"dynamic": entry}, "full": {"dynamic": entry, "clutter": entry}}
    names = ["ground", "high object", "short object", "phantom"]
    confusion = np.array([[50, 1, 0, 0], [2, 30, 1, 0], [0, 1, 20, 2], [0, 0, 3, 17]])
    scores = scores_from_confusion(confusion, names, macro_exclude=("ground",)).as_dict()
    truth = np.r_[np.ones(20, bool), np.zeros(30, bool)]
    guess = np.r_[np.ones(18, bool), np.zeros(30, bool), np.ones(2, bool)]
    phantom_metrics = {
        "pillar": scores,
        "pillar_raw": scores,
        "point": scores,
        "phantom_points": {"mmsclean": binary_scores(truth, guess).as_dict()},
    }
    guardrail_metrics = {
        "reference": "simulated guardrail points",
        "slice_raw": binary_scores(truth, guess).as_dict(),
        "slice": binary_scores(truth, truth).as_dict(),
        "point": binary_scores(truth, guess).as_dict(),
    }
    jobs = server.data_dir / "jobs"
    clutter_report = write_report(
        jobs / "c", {"counts": {"points": 100, "removed_points": 11}, "metrics": clutter_metrics}
    )
    add(
        engine,
        succeeded_job(survey_id, "run:clutter", {}, clutter_report),
        succeeded_job(
            survey_id,
            "run:phantom",
            {},
            write_report(
                jobs / "p",
                {
                    "counts": {"pillars": 9, "pillars_per_class": {"ground": 5, "phantom": 4}},
                    "metrics": phantom_metrics,
                },
            ),
        ),
        succeeded_job(
            survey_id,
            "run:guardrail",
            {},
            write_report(jobs / "g", {"metrics": guardrail_metrics}),
        ),
    )
    with Session(engine) as session:
        instances = [
            ClutterInstance(survey_id=survey_id, frame_id="map", instance_index=i, class_name="car")
            for i in range(4)
        ]
        session.add_all(instances)
        session.flush()
        session.add_all(
            [
                ClutterDecision(instance_id=instances[0].id, decision=Decision.approved),
                ClutterDecision(instance_id=instances[1].id, decision=Decision.approved),
                ClutterDecision(instance_id=instances[2].id, decision=Decision.rejected),
            ]
        )
        session.commit()

    response = reviewer.get(f"/surveys/{survey_id}/exports/qa-report.html")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/html")
    assert 'filename="Main-Street-qa-report.html"' in response.headers["content-disposition"]
    page = response.text
    assert "<h1>QA report: Main Street</h1>" in page
    # clutter: OA 95.0, clutter omission 2/10 = 20.0, commission 3/11 = 27.3
    assert "overall accuracy [%]" in page and "SA [%]" in page and "AA [%]" in page
    assert "<td>95.0</td><td>20.0</td><td>27.3</td>" in page
    # phantom: per-class table with the paper's overall row (ground left out)
    phantom_p = 100 * 17 / 19
    assert f"<td>phantom</td><td>{phantom_p:.1f}</td><td>85.0</td>" in page
    assert "overall (mean of high object, short object, phantom)" in page
    # a group of counts is one row per member, not a Python dict (issue 20)
    assert "<td>pillars per class: phantom</td><td>4</td>" in page and "{&#x27;" not in page
    # guardrail: corrected slices perfect, CNN slices P 18/20
    assert "<td>slices (corrected)</td><td>100.0</td><td>100.0</td><td>100.0</td>" in page
    assert "<td>slices (CNN)</td><td>90.0</td><td>90.0</td>" in page
    # review state: 3 human labels by ann (one phantom), clutter decisions 2 / 1 / 1
    assert "<td>ann</td><td>1</td><td>1</td><td>0</td><td>1</td><td>3</td>" in page
    assert "<td>4</td><td>2</td><td>1</td><td>1</td>" in page
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(images) >= 5  # error matrices, confusion matrices, F bars, label bars
    decoded = cv2.imdecode(np.frombuffer(base64.b64decode(images[0]), np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None and decoded.shape[0] > 100 and decoded.shape[1] > 100
    assert "http://" not in page and "https://" not in page  # self-contained
    assert exports_audited(engine, survey_id)[-1] == "export.qa_report"


def test_qa_report_without_runs(server: Server, reviewer: httpx.Client, tmp_path: Path) -> None:
    path = write_laz(tmp_path / "bare.laz", np.zeros((3, 3)))
    with server.client() as admin:
        bare = admin.post(
            "/surveys/upload", params={"filename": "bare.laz"}, content=path.read_bytes()
        ).json()
    page = reviewer.get(f"/surveys/{bare['id']}/exports/qa-report.html").text
    assert page.count("No finished run of this pipeline") == 3
    assert "No human pillar labels yet." in page


def mmsclean_export(server: Server, *args: str) -> subprocess.CompletedProcess:
    return mmsclean("export", *args, env={"MMSCLEAN_DATA_DIR": str(server.data_dir)})


def test_command_line_export_matches_the_downloads(
    server: Server, survey_id: int, engine: Engine, reviewer: httpx.Client, tmp_path: Path
) -> None:
    """`mmsclean export` writes what the dashboard downloads, from the same store, audited."""
    base = f"/surveys/{survey_id}/exports"
    job_dir = server.data_dir / "jobs" / "clutter-cli"
    rng = np.random.default_rng(2)
    cleaned = write_laz(job_dir / "cleaned.laz", rng.uniform(0, 5, (30, 3)))
    removed = write_laz(job_dir / "removed.laz", rng.uniform(0, 5, (5, 3)))
    add(
        engine,
        succeeded_job(survey_id, "run:clutter", {"cleaned": cleaned, "removed": removed}, None),
    )
    removed.unlink()
    for what, url in (("cleaned-laz", "cleaned.laz"), ("pillars-csv", "pillars.csv")):
        done = mmsclean_export(server, str(survey_id), what, "--out", str(tmp_path / url))
        assert done.returncode == 0, done.stderr
        assert (tmp_path / url).read_bytes() == reviewer.get(f"{base}/{url}").content
    done = mmsclean_export(
        server,
        "Main Street",
        "guardrails",
        "--out",
        str(tmp_path / "g.zip"),
        "--mesh-format",
        "obj",
    )
    assert done.returncode == 0, done.stderr
    with zipfile.ZipFile(tmp_path / "g.zip") as zf:
        assert sorted(zf.namelist()) == ["Main-Street-guardrail-000-pipe.obj", "manifest.json"]
    done = mmsclean_export(
        server, str(survey_id), "pillars-npz", "--include-model", "--out", str(tmp_path / "p.npz")
    )
    assert done.returncode == 0, done.stderr
    assert len(np.load(tmp_path / "p.npz")["cell_id"]) == 4
    done = mmsclean_export(server, str(survey_id), "qa-report", "--out", str(tmp_path / "qa.html"))
    assert done.returncode == 0 and "QA report: Main Street" in (tmp_path / "qa.html").read_text()
    with Session(engine) as session:
        cli = session.exec(select(AuditEvent).where(AuditEvent.action.startswith("export."))).all()
    assert sum(e.payload.get("via") == "command line" for e in cli) == 5

    # refusals: one line each, nothing written
    refused = [
        (("999", "qa-report", "--out", str(tmp_path / "x.html")), "survey 999 not found"),
        ((str(survey_id), "removed-laz", "--out", str(tmp_path / "r.laz")), "gone from disk"),
        ((str(survey_id), "qa-report", "--out", str(tmp_path / "qa.html")), "--overwrite"),
        ((str(survey_id), "everything", "--out", str(tmp_path / "e")), "must be one of"),
    ]
    for args, message in refused:
        done = mmsclean_export(server, *args)
        assert done.returncode != 0 and message in done.stderr, done.stderr
        assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.html").exists() and not (tmp_path / "r.laz").exists()
    assert not list(tmp_path.glob(".*.partial"))


def test_job_files_follow_the_export_rule(
    server: Server,
    survey_id: int,
    engine: Engine,
    reviewer: httpx.Client,
    annotator: httpx.Client,
) -> None:
    """A run's cleaned map is reviewer-only under /jobs/{id}/files as under the survey's
    exports; its log and report stay readable by annotators, whose results listing shows only
    those."""
    folder = server.data_dir / "jobs" / "phantom-files"
    rng = np.random.default_rng(3)
    cleaned = write_laz(folder / "cleaned.laz", rng.uniform(0, 5, (30, 3)))
    (folder / "job.log").write_text("started\n")
    (folder / "report.json").write_text('{"counts": {}}')
    (folder / "labels").mkdir()
    np.save(folder / "labels" / "map.npy", np.zeros(30, np.uint8))
    (folder / "pillars.npz").write_bytes(b"npz")
    (folder / "guardrails").mkdir()
    (folder / "guardrails" / "0.glb").write_bytes(b"glb")
    job = succeeded_job(survey_id, "run:phantom", {"cleaned": cleaned}, folder / "report.json")
    job.result_path = str(folder)
    job.log_path = str(folder / "job.log")
    add(engine, job)
    with Session(engine) as session:
        job_id = session.exec(select(Job.id).where(Job.result_path == str(folder))).one()
    protected = ["cleaned.laz", "labels/map.npy", "pillars.npz", "guardrails/0.glb"]
    assert annotator.get(f"/surveys/{survey_id}/exports/cleaned.laz").status_code == 403
    for name in protected:
        refused = annotator.get(f"/jobs/{job_id}/files/{name}")
        assert refused.status_code == 403, name
        assert "needs the reviewer role" in refused.json()["detail"]
        assert reviewer.get(f"/jobs/{job_id}/files/{name}").status_code == 200, name
    for name in ("job.log", "report.json"):
        assert annotator.get(f"/jobs/{job_id}/files/{name}").status_code == 200, name
    assert annotator.get(f"/jobs/{job_id}/log").text == "started\n"
    listed = {
        who: {f["name"] for f in client.get(f"/jobs/{job_id}/results").json()["files"]}
        for who, client in (("annotator", annotator), ("reviewer", reviewer))
    }
    assert listed["annotator"] == {"job.log", "report.json"}
    assert listed["reviewer"] == {"job.log", "report.json", *protected}


# --- what mapping teams expect: SemanticKITTI labels, PCD, classified LAZ with the CRS (issue 20)


def add_frames_survey(engine: Engine, name: str, fmt: str, source: str, counts: list[int]) -> int:
    with Session(engine) as session:
        survey = Survey(name=name, format=fmt, source_path=source, frame_count=len(counts))
        session.add(survey)
        session.flush()
        for i, count in enumerate(counts):
            session.add(
                Frame(
                    survey_id=survey.id, frame_index=i, frame_id=f"{i:06d}", point_count=count,
                    pose=[0.0] * 16,
                )
            )  # fmt: skip
        session.commit()
        return survey.id


def test_missing_runs_are_4xx_naming_what_is_missing(
    server: Server, engine: Engine, reviewer: httpx.Client
) -> None:
    bare = add_frames_survey(engine, "bare drive", "semantickitti", "/nowhere/07", [5])
    for name in MAP_FORMATS:
        response = reviewer.get(f"/surveys/{bare}/exports/{name}")
        assert response.status_code == 404, name
        assert response.json()["detail"] == (
            f"survey {bare} has no finished clutter or phantom run; run the clutter or phantom "
            "pipeline first"
        )
    response = reviewer.get(f"/surveys/{bare}/exports/semantickitti-labels.zip")
    assert response.status_code == 404
    assert response.json()["detail"] == (
        f"survey {bare} has no finished clutter run; run the clutter pipeline first"
    )
    # a phantom run gives maps but no SemanticKITTI labels; a clutter run without review units
    # (as an old one) is named
    folder = server.data_dir / "jobs" / "bare-phantom"
    cleaned = write_laz(folder / "cleaned.laz", np.random.default_rng(4).uniform(0, 5, (9, 3)))
    add(engine, succeeded_job(bare, "run:phantom", {"cleaned": cleaned}, None))
    assert reviewer.get(f"/surveys/{bare}/exports/cleaned.pcd").status_code == 200
    assert reviewer.get(f"/surveys/{bare}/exports/semantickitti-labels.zip").status_code == 404
    add(engine, succeeded_job(bare, "run:clutter", {"cleaned": cleaned}, None))
    response = reviewer.get(f"/surveys/{bare}/exports/semantickitti-labels.zip")
    assert response.status_code == 404 and "wrote no review units" in response.json()["detail"]
    assert list((server.data_dir / "cache" / "exports").glob("*.zip")) == []


def review_units(folder: Path, frame_id: str, owner: list[int], removed: list[bool]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        folder / f"{frame_id}.npz",
        instance=np.array(owner, np.int32),
        removed=np.array(removed, bool),
        in_view=np.ones(len(owner), bool),
    )


def test_semantickitti_labels_per_frame(
    server: Server, engine: Engine, reviewer: httpx.Client, tmp_path: Path
) -> None:
    """One .label per frame, one word per point: moving objects get SemanticKITTI's moving ids,
    parked clutter the static ones, reviewers' verdicts applied (rejected: kept, unlabelled;
    approved: removed), tracked objects one instance id along the drive."""
    sid = add_frames_survey(engine, "seq four", "semantickitti", "/nowhere/04", [12, 7, 5])
    run = server.data_dir / "jobs" / "skitti-run"
    units = run / "instances"
    T, F = True, False
    review_units(units, "000000", [-1, -1, 0, 0, 0, 1, 1, 2, 2, 3, 3, 4],
                 [F, F, T, T, F, T, T, T, T, T, F, F])  # fmt: skip
    review_units(units, "000001", [0, 0, 0, -1, -1, 1, 1], [F, F, F, F, F, T, T])
    review_units(units, "000002", [-1] * 5, [F] * 5)
    rows = []
    for frame_id, k, name, moving, track in [
        ("000000", 0, "car", True, 5),
        ("000000", 1, "person", False, None),
        ("000000", 2, "free-space", True, None),
        ("000000", 3, "truck", False, None),  # rejected below: its points stay, unlabelled
        ("000000", 4, "bicycle", False, None),  # kept by the run: a parked bicycle
        ("000001", 0, "motorcycle", True, None),  # approved below: all its points go
        ("000001", 1, "moved-track", True, 9),
    ]:
        mask = units / frame_id / f"{k}.png"
        mask.parent.mkdir(exist_ok=True)
        mask.write_bytes(b"png")
        rows.append({"frame_id": frame_id, "instance_index": k, "class_name": name,
                     "point_count": 1, "mask_path": str(mask), "moving": moving,
                     "track_id": track})  # fmt: skip
    with Session(engine) as session:
        replace_instances(session, sid, rows, None)
        ids = {(i.frame_id, i.instance_index): i.id for i in list_instances(session, sid)[1]}
        decide(session, sid, [
            DecisionWrite(ids[("000000", 3)], 1, Decision.rejected),
            DecisionWrite(ids[("000001", 0)], 1, Decision.approved),
        ], None)  # fmt: skip
    add(engine, succeeded_job(sid, "run:clutter", {"instances": units}, None))

    response = reviewer.get(f"/surveys/{sid}/exports/semantickitti-labels.zip")
    assert response.status_code == 200, response.text
    assert 'filename="seq-four-semantickitti-labels.zip"' in response.headers["content-disposition"]
    with zipfile.ZipFile(io.BytesIO(response.content)) as zf:
        zf.extractall(tmp_path)
        manifest = json.loads(zf.read("manifest.json"))
        readme = zf.read("README.txt").decode()
    labels = tmp_path / "sequences" / "04" / "labels"
    assert sorted(p.name for p in labels.iterdir()) == [f"00000{i}.label" for i in range(3)]
    read = {
        i: read_label_file(labels / f"00000{i}.label", n) for i, n in enumerate([12, 7, 5])
    }  # the file's length is checked against the frame's points by the reader
    assert (labels / "000000.label").stat().st_size == 4 * 12
    # tracks 5 and 9 are ids 6 and 10; untracked instances take 11, 12, ... in order
    assert read[0]["semantic"].tolist() == [0, 0, 252, 252, 0, 30, 30, 259, 259, 0, 0, 11]
    assert read[0]["instance"].tolist() == [0, 0, 6, 6, 0, 11, 11, 12, 12, 0, 0, 14]
    assert read[1]["semantic"].tolist() == [255, 255, 255, 0, 0, 259, 259]
    assert read[1]["instance"].tolist() == [15, 15, 15, 0, 0, 10, 10]
    assert read[2]["semantic"].tolist() == [0] * 5
    raw = np.fromfile(labels / "000001.label", dtype="<u4")
    assert raw[0] == (15 << 16) | 255  # little-endian, semantic low, instance high
    assert manifest["job_kind"] == "run:clutter" and manifest["decisions"]["approved"] == 1
    assert manifest["ids"]["252"] == "moving-car" and manifest["ids"]["30"] == "person"
    assert manifest["points_per_id"]["259 moving-other-vehicle"] == 4
    assert f"job {manifest['job_id']}" in readme and "255  moving-motorcyclist" in readme
    assert exports_audited(engine, sid) == ["export.semantickitti_labels"]

    # the command line writes the same files
    out = tmp_path / "cli.zip"
    done = mmsclean_export(server, str(sid), "semantickitti-labels", "--out", str(out))
    assert done.returncode == 0, done.stderr
    with zipfile.ZipFile(out) as zf, zipfile.ZipFile(io.BytesIO(response.content)) as api:
        for name in api.namelist():
            if name.endswith(".label"):
                assert zf.read(name) == api.read(name)

    # a membership file whose points disagree with the frame is refused, not exported half
    review_units(units, "000002", [-1] * 4, [F] * 4)
    response = reviewer.get(f"/surveys/{sid}/exports/semantickitti-labels.zip")
    assert response.status_code == 422
    assert "4 points, frame 000002 has 5" in response.json()["detail"]


def drive(origin: np.ndarray) -> SimSurvey:
    """Two frames of 10 and 6 points with reflectance, posed near `origin`."""
    rng = np.random.default_rng(8)
    frames = []
    for k, n in enumerate((10, 6)):
        pose = np.eye(4)
        pose[:3, 3] = origin + [2.0 * k, 0.0, 0.0]
        cloud = PointCloud(rng.uniform(-5, 5, (n, 3)), intensity=rng.uniform(0, 1, n))
        frames.append(SimFrame(k, f"{k:06d}", pose, None, n, _load_points=lambda c=cloud: c))
    return SimSurvey("drive", Path("drive"), "sim", frames)


def test_maps_for_other_tools_with_the_survey_crs(
    server: Server, engine: Engine, reviewer: httpx.Client, tmp_path: Path
) -> None:
    """A survey imported from a LAZ with a WKT CRS: its maps carry that CRS, the classified map
    joins both with ASPRS classes as `app.io.asprs` maps the labels, the PCD reads back through
    `app.io.pcd` with the same points and labels."""
    origin = np.array([512_000.0, 5_400_000.0, 300.0])
    source = write_laz(
        tmp_path / "geo.laz", np.random.default_rng(5).uniform(0, 9, (20, 3)) + origin
    )
    las = laspy.read(source)
    las.header.vlrs.append(WktCoordinateSystemVlr(WKT))
    las.header.global_encoding.wkt = True
    las.write(source)
    response = reviewer.post(
        "/surveys/upload", params={"filename": "geo street.laz"}, content=source.read_bytes()
    )
    assert response.status_code == 201, response.text
    sid = response.json()["id"]

    survey = drive(origin)
    removed = [np.arange(10) % 3 == 0, np.zeros(6, bool)]
    job_dir = server.data_dir / "jobs" / "geo-clutter"
    maps = write_frame_maps(job_dir, "", survey, np.arange(2), removed, None, maps_offset(survey))
    files = {kind: job_dir / maps[kind] for kind in ("cleaned", "removed")}
    add(engine, succeeded_job(sid, "run:clutter", files, None))
    base = f"/surveys/{sid}/exports"

    cleaned = reviewer.get(f"{base}/cleaned.laz")
    assert cleaned.status_code == 200, cleaned.text
    assert "WKT from the header" in cleaned.headers["x-mmsclean-crs"]
    got = laspy.read(io.BytesIO(cleaned.content))
    assert got.header.global_encoding.wkt
    assert [v.string for v in got.header.vlrs if isinstance(v, WktCoordinateSystemVlr)] == [WKT]
    original = laspy.read(files["cleaned"])
    assert np.array_equal(got.X, original.X) and len(got.points) == 12

    classified = reviewer.get(f"{base}/classified.laz")
    assert classified.status_code == 200, classified.text
    assert (
        'filename="geo-street-clutter-classified.laz"' in classified.headers["content-disposition"]
    )
    joined = laspy.read(io.BytesIO(classified.content))
    assert len(joined.points) == 16 and joined.header.global_encoding.wkt
    labels = np.asarray(joined.mmsclean_label)
    assert labels.tolist() == [0] * 12 + [1] * 4  # the cleaned map, then the removed one
    assert np.array_equal(joined.classification, to_asprs(labels, CLUTTER_LABEL_TO_ASPRS))
    assert set(np.asarray(joined.classification).tolist()) == {1, REMOVED_CLUTTER_ASPRS}
    world = np.column_stack([joined.x, joined.y, joined.z])

    whole = reviewer.get(f"{base}/map.pcd")
    assert whole.status_code == 200, whole.text
    (tmp_path / "map.pcd").write_bytes(whole.content)
    read = read_pcd(tmp_path / "map.pcd")
    assert read.reference_label_kinds == ("label",)
    points = read.frames[0].points()
    survey_origin = np.asarray(reviewer.get(f"/surveys/{sid}").json()["origin"])
    np.testing.assert_allclose(points.xyz + survey_origin, world, atol=1e-3)
    assert points.extra["label"].tolist() == labels.tolist()
    assert np.array_equal(points.intensity, np.asarray(joined.intensity, np.float32))
    assert b"origin 512000.000 5400000.000 300.000" in whole.content[:2000]
    only_kept = reviewer.get(f"{base}/cleaned.pcd")
    (tmp_path / "cleaned.pcd").write_bytes(only_kept.content)
    kept = read_pcd(tmp_path / "cleaned.pcd").frames[0].points()
    assert len(kept.xyz) == 12 and not kept.extra["label"].any()
    assert exports_audited(engine, sid) == [
        "export.cleaned_laz", "export.classified_laz", "export.map_pcd", "export.cleaned_pcd"
    ]  # fmt: skip
    for what in ("classified-laz", "map-pcd"):
        out = tmp_path / f"cli-{what}"
        done = mmsclean_export(server, str(sid), what, "--out", str(out))
        assert done.returncode == 0, done.stderr
        url = {"classified-laz": "classified.laz", "map-pcd": "map.pcd"}[what]
        assert out.read_bytes() == reviewer.get(f"{base}/{url}").content, what
    assert not list(tmp_path.glob(".*partial*"))

    # a survey that records no CRS gets none, and the answer says so
    sk = add_frames_survey(engine, "no crs", "semantickitti", "/nowhere/05", [16])
    add(engine, succeeded_job(sk, "run:clutter", files, None))
    plain = reviewer.get(f"/surveys/{sk}/exports/classified.laz")
    assert (
        plain.headers["x-mmsclean-crs"]
        == "a semantickitti survey records no CRS (only LAS / LAZ headers do)"
    )
    assert not laspy.read(io.BytesIO(plain.content)).header.global_encoding.wkt
    as_is = reviewer.get(f"/surveys/{sk}/exports/removed.laz")
    assert as_is.content == files["removed"].read_bytes()


def pairs(frame: np.ndarray, index: np.ndarray) -> set[tuple[int, int]]:
    return set(zip(frame.tolist(), index.tolist(), strict=True))


def test_combined_maps_leave_out_what_either_run_removed(
    server: Server, tmp_path: Path, engine: Engine, reviewer: httpx.Client
) -> None:
    """Issue 20: exports cover clutter, phantom and both combined. Points are known by their
    (source frame, source index): the combined cleaned map is the clutter run's cleaned points
    without those the phantom run removed; the combined removed map is the union."""
    sid = add_frames_survey(engine, "Combined", "semantickitti", "/nowhere/09", [10, 10])
    frame = np.repeat([0, 1], 10).astype(np.uint32)
    index = np.tile(np.arange(10), 2).astype(np.uint32)
    rng = np.random.default_rng(5)
    xyz = rng.uniform(0, 5, (20, 3)) + [600_000.0, 5_000_000.0, 80.0]
    clutter_gone = (frame == 0) & (index < 3)  # 3 points
    phantom_gone = (frame == 1) & (index >= 6) | (frame == 0) & (index == 2)  # 5, one shared

    def write(path: Path, mask: np.ndarray, label: int) -> Path:
        return write_laz(path, xyz[mask], source_frame=frame[mask], source_index=index[mask],
                         mmsclean_label=np.full(mask.sum(), label, np.uint8))  # fmt: skip

    jobs = server.data_dir / "jobs"
    clutter = {"cleaned": write(jobs / "c" / "cleaned.laz", ~clutter_gone, 0),
               "removed": write(jobs / "c" / "removed.laz", clutter_gone, 1)}  # fmt: skip
    phantom = {"cleaned": write(jobs / "p" / "cleaned.laz", ~phantom_gone, 0),
               "removed": write(jobs / "p" / "removed.laz", phantom_gone, 3)}  # fmt: skip
    add(engine, succeeded_job(sid, "run:clutter", clutter, None))
    add(engine, succeeded_job(sid, "run:phantom", phantom, None))

    def keys(content: bytes) -> set[tuple[int, int]]:
        path = tmp_path / "download.laz"
        path.write_bytes(content)
        cloud = read_las_points(path)
        return pairs(cloud.extra["source_frame"], cloud.extra["source_index"])

    either = clutter_gone | phantom_gone
    cleaned = reviewer.get(f"/surveys/{sid}/exports/cleaned.laz?source=combined")
    assert cleaned.status_code == 200, cleaned.text
    assert 'filename="Combined-combined-cleaned.laz"' in cleaned.headers["content-disposition"]
    assert keys(cleaned.content) == pairs(frame[~either], index[~either])
    removed = reviewer.get(f"/surveys/{sid}/exports/removed.laz?source=combined")
    assert keys(removed.content) == pairs(frame[either], index[either])
    path = tmp_path / "removed.laz"
    path.write_bytes(removed.content)
    labels = read_las_points(path).extra["mmsclean_label"]
    assert sorted(labels.tolist()) == [1, 1, 1, 3, 3, 3, 3]  # each point as its run wrote it
    # only the cleaned and removed LAZ maps combine: the others refuse it (422, not a 500)
    for other in ("classified.laz", "cleaned.pcd", "map.pcd"):
        refused = reviewer.get(f"/surveys/{sid}/exports/{other}?source=combined")
        assert refused.status_code == 422 and "source" in refused.json()["detail"]
    # the command line writes the same map
    out = tmp_path / "combined.laz"
    done = mmsclean_export(
        server, str(sid), "cleaned-laz", "--source", "combined", "--out", str(out)
    )
    assert done.returncode == 0, done.stderr
    assert keys(out.read_bytes()) == pairs(frame[~either], index[~either])
    done = mmsclean_export(server, str(sid), "map-pcd", "--source", "combined", "--out", "x.pcd")
    assert done.returncode != 0 and "cleaned-laz and removed-laz only" in done.stderr
    # without a phantom run there is nothing to combine: 404 naming it
    alone = add_frames_survey(engine, "Alone", "semantickitti", "/nowhere/10", [10, 10])
    add(engine, succeeded_job(alone, "run:clutter", clutter, None))
    missing = reviewer.get(f"/surveys/{alone}/exports/cleaned.laz?source=combined")
    assert missing.status_code == 404 and "phantom" in missing.json()["detail"]
