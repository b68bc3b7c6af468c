"""A file uploaded as part of a survey can never be loaded as a model (issue 15, section 1):
jobs name models by registry id, and checkpoints load as data only (weights_only=True).

The attack, through a real server: an annotator uploads a zip holding a survey and a pickle
`evil.pt` whose unpickling would create a marker file, then queues a guardrail (and a phantom)
run with `model_path` pointing at it."""

from __future__ import annotations

import io
import os
import shlex
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import torch
from sqlmodel import Session

from app.core.errors import InputError
from app.jobs.task_config import MODEL_PATH_REFUSED
from app.pipelines.guardrail.classifier import load_heads
from app.pipelines.guardrail.pipeline import DEFAULT_MODEL as DEFAULT_CLASSIFIER
from app.pipelines.phantom.model import DEFAULT_MODEL, load_model
from app.simulate.survey import SimulationConfig, simulate
from app.store.db import make_engine
from app.store.model_versions import ensure_shipped_version
from app.store.models import Pipeline
from tests.api.server import Server

WAIT_S = 120.0


class Payload:
    """Unpickling runs `touch MARKER` (as the process that loads it)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {shlex.quote(str(self.marker))}",))


def evil_checkpoint(path: Path, marker: Path) -> Path:
    """A `.pt` shaped like a guardrail checkpoint whose heads are the payload."""
    torch.save({"heads": Payload(marker), "card": {}}, path)
    return path


def upload_with_pickle(client: httpx.Client, drive: Path, marker: Path) -> Path:
    """Upload a zip of a simulated KITTI-like drive with `evil.pt` inside; the pickle's path on
    the server."""
    evil = evil_checkpoint(drive.parent / "evil.pt", marker)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as zf:
        for path in sorted(drive.rglob("*")):
            if path.is_file():
                zf.write(path, f"seq/{path.relative_to(drive)}")
        zf.write(evil, "seq/data/evil.pt")
    response = client.post(
        "/surveys/upload", params={"filename": "drive.zip"}, content=buffer.getvalue()
    )
    assert response.status_code == 201, response.text
    survey = response.json()
    stored = Path(survey["source_path"]) / "data" / "evil.pt"
    assert stored.is_file()  # the pickle is on the server, inside the data dir
    return stored


def wait_for_workers(client: httpx.Client) -> None:
    """Until no job is queued or running (whatever was queued has had its chance to run)."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        jobs = client.get("/jobs").json()
        if not any(j["status"] in ("queued", "running") for j in jobs):
            return
        time.sleep(0.2)
    raise AssertionError(f"jobs still active after {WAIT_S} s")


@pytest.fixture(scope="module")
def annotator(server: Server) -> Iterator[httpx.Client]:
    with server.add_user("uploader", "annotator") as client:
        yield client


@pytest.fixture(scope="module")
def survey_and_pickle(
    server: Server, annotator: httpx.Client, tmp_path_factory: pytest.TempPathFactory
) -> tuple[int, Path, Path]:
    work = tmp_path_factory.mktemp("attack")
    drive = work / "drive"
    simulate(SimulationConfig(length=6, camera=False, compressed=True), drive, True, None)
    marker = work / "pwned"
    stored = upload_with_pickle(annotator, drive, marker)
    survey_id = annotator.get("/surveys").json()[0]["id"]
    return survey_id, stored, marker


def test_a_model_path_to_an_uploaded_pickle_is_refused(
    annotator: httpx.Client, survey_and_pickle: tuple[int, Path, Path]
) -> None:
    survey_id, evil, marker = survey_and_pickle
    answers = {
        kind: annotator.post(
            "/jobs",
            json={"kind": kind, "survey_id": survey_id, "config": {"model_path": str(evil)}},
        )
        for kind in ("run:guardrail", "run:phantom")
    }
    wait_for_workers(annotator)
    assert not marker.exists(), "the uploaded pickle ran on the server"
    for kind, response in answers.items():
        assert response.status_code == 422, (kind, response.text)
        assert response.json()["detail"] == f"config.model_path: {MODEL_PATH_REFUSED}"
    assert "config.model_id" in MODEL_PATH_REFUSED and "GET /models" in MODEL_PATH_REFUSED


def test_jobs_name_a_model_by_registry_id(
    server: Server, annotator: httpx.Client, survey_and_pickle: tuple[int, Path, Path]
) -> None:
    survey_id, _, marker = survey_and_pickle
    engine = make_engine(f"sqlite:///{server.data_dir / 'mmsclean.sqlite3'}")
    with Session(engine) as session:
        phantom = ensure_shipped_version(session, Pipeline.phantom, DEFAULT_MODEL, {}).id
        guardrail = ensure_shipped_version(session, Pipeline.guardrail, DEFAULT_CLASSIFIER, {}).id
    engine.dispose()
    listed = {m["id"]: m["pipeline"] for m in annotator.get("/models").json()}
    assert listed == {phantom: "phantom", guardrail: "guardrail"}
    for config, problem in (
        ({"model_id": phantom}, f"model version {phantom} is a phantom model"),
        ({"model_id": 999_999}, "no model version 999999"),
        ({"model_id": 0}, "greater than or equal to 1"),
        ({"model_id": str(marker)}, "valid integer"),
    ):
        response = annotator.post(
            "/jobs", json={"kind": "run:guardrail", "survey_id": survey_id, "config": config}
        )
        assert response.status_code == 422, response.text
        detail = response.json()["detail"]
        assert detail.startswith("config.model_id:") and problem in detail, detail
    created = annotator.post(
        "/jobs",
        json={"kind": "run:phantom", "survey_id": survey_id, "config": {"model_id": phantom}},
    )
    assert created.status_code == 201, created.text
    assert annotator.post(f"/jobs/{created.json()['id']}/cancel").status_code == 200
    wait_for_workers(annotator)


def test_the_loaders_refuse_the_pickle_without_running_it(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    evil = evil_checkpoint(tmp_path / "evil.pt", marker)
    for load in (load_heads, load_model):
        with pytest.raises(InputError) as caught:
            load(evil)
        message = str(caught.value)
        assert message.startswith(f"{evil}: not a ") and "\n" not in message, message
        assert "other than tensors and plain types" in message
    assert not marker.exists()
