"""Start-up clean-up (issue 15, section 5): a server killed during an upload leaves its
`surveys/<uuid>/` folder behind; the next start removes folders no row owns (logging each with
its size) and keeps every folder a survey or a job owns, and anything it did not make."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np
import pytest

from app.io.las import write_laz
from tests.api.server import Server


def fill(folder: Path, name: str, size: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_bytes(os.urandom(size))
    return path


@pytest.fixture(scope="module")
def restarted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A server that uploaded a survey and ran a job, killed, given orphans, started again."""
    data_dir = tmp_path_factory.mktemp("orphans") / "var"
    server = Server(data_dir, env={"MMSCLEAN_SAMPLE_DIR": ""}).start()
    try:
        with server.client() as admin:
            xyz = np.random.default_rng(0).uniform(0, 20, (300, 3))
            laz = write_laz(data_dir.parent / "map.laz", xyz).read_bytes()
            upload = admin.post("/surveys/upload", params={"filename": "map.laz"}, content=laz)
            assert upload.status_code == 201, upload.text
            survey = upload.json()
            source = Path(survey["source_path"])
            job = admin.post(
                "/jobs", json={"kind": "import:survey", "config": {"path": str(source)}}
            )
            assert job.status_code == 201, job.text
            job_id = job.json()["id"]
    finally:
        server.kill_9()
    owned_upload = source.parent
    owned_job = data_dir / "jobs" / str(job_id)
    fill(owned_job, "kept.txt", 10)  # the worker may not have reached it before the kill
    surveys_dir = data_dir / "surveys"
    orphan_upload = surveys_dir / uuid.uuid4().hex
    fill(orphan_upload, ".upload.zip", 3 * 2**20)  # killed while receiving an archive
    fill(orphan_upload / "data" / "velodyne_points", "0000.bin", 2**20)
    orphan_job = data_dir / "jobs" / str(job_id + 1000)
    fill(orphan_job, "labels.npy", 2**19)
    not_ours = fill(surveys_dir / "by-hand", "notes.txt", 10).parent
    server = Server(data_dir, env={"MMSCLEAN_SAMPLE_DIR": ""}).start()
    server.stop()
    return {
        "log": server.log(),
        "owned": [owned_upload, owned_job, not_ours],
        "orphans": [orphan_upload, orphan_job],
        "source": source,
    }


def test_orphaned_upload_and_job_folders_are_removed(restarted: dict) -> None:
    for folder in restarted["orphans"]:
        assert not folder.exists(), folder


def test_owned_and_foreign_folders_are_kept(restarted: dict) -> None:
    for folder in restarted["owned"]:
        assert folder.is_dir(), folder
    assert restarted["source"].is_file()


def test_each_removal_is_logged_with_its_size(restarted: dict) -> None:
    upload, job = restarted["orphans"]
    lines = restarted["log"].splitlines()
    assert any(str(upload) in line and "(4.0 MB" in line for line in lines), restarted["log"]
    assert any(str(job) in line and "(0.5 MB" in line for line in lines), restarted["log"]
