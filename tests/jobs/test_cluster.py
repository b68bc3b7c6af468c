"""Tiles on a real Dask cluster: a local cluster of two worker processes, and a real scheduler
with two real workers started as a team would, run the phantom pipeline's tiles; the labels are
those of the tiles run in this process, even when a worker is killed mid-run."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from app.core.settings import Settings
from app.io import open_survey
from app.jobs.cluster import close_clients, tile_client, tile_map
from app.pipelines.phantom.pipeline import PhantomPipeline
from app.pipelines.phantom.tiled import run_phantom_tiled
from tests.api.server import free_port

ROOT = Path(__file__).resolve().parents[2]


def test_a_local_cluster_runs_the_tiles(tmp_path: Path, monkeypatch) -> None:
    """The tiles and the index pass (in parts of 16 frames: the sample has 59) on the
    cluster: the labels of the run in this process. There the 58 m drive is 3 tiles of 25 m;
    on the 2 workers, 2 equal tiles (`TileLayout.along(workers=)`)."""
    import app.io.tile_index as tile_index

    survey = open_survey(ROOT / "data_samples" / "urban-60m", "sim")
    pipeline = PhantomPipeline(model_path=ROOT / "models" / "phantom" / "phantom_cnn.pt")
    here = run_phantom_tiled(pipeline, survey, tmp_path / "here", length=25.0)
    settings = Settings(data_dir=tmp_path, workers=2, sample_dir="")
    try:
        client = tile_client(settings)
        assert len(client.scheduler_info()["workers"]) == 2
        monkeypatch.setattr(tile_index, "PART_FRAMES", 16)
        seen = []
        there = run_phantom_tiled(
            pipeline, survey, tmp_path / "there", length=25.0, map_tiles=tile_map(settings),
            progress=lambda stage, fraction: seen.append(fraction),
        )  # fmt: skip
        assert tile_client(settings) is client  # one cluster per process
    finally:
        close_clients()
    assert here.index.count == 3 and there.index.count == 2 and seen == [0.0, 0.5, 1.0]
    for frame in survey.frames:
        name = f"{frame.frame_id}.npy"
        assert np.array_equal(
            np.load(tmp_path / "here" / "labels" / name),
            np.load(tmp_path / "there" / "labels" / name),
        )


def test_a_scheduler_address_is_checked() -> None:
    assert Settings(dask_scheduler="tcp://scheduler:8786").dask_scheduler == "tcp://scheduler:8786"
    assert Settings(dask_scheduler="").dask_scheduler is None
    with pytest.raises(ValueError, match="dask_scheduler"):
        Settings(dask_scheduler="file:///etc/passwd")


@pytest.fixture
def dask_cluster(tmp_path: Path):
    """A real `dask scheduler` and two `dask worker` processes, as a team's cluster runs them
    (the workers import this package from the repository, like the docker image's)."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    dask = str(Path(sys.executable).with_name("dask"))
    logs = tmp_path / "dask-logs"
    logs.mkdir()
    commands = {
        "scheduler": ["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
        **{f"w{k}": ["worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                     "--name", f"w{k}", "--memory-limit", "2GiB",
                     "--preload", "app.jobs.tile_preload"] for k in range(2)},
    }  # fmt: skip
    files = contextlib.ExitStack()
    processes = [
        subprocess.Popen(
            [dask, *args], env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
            stderr=files.enter_context((logs / name).open("w")),
        )
        for name, args in commands.items()
    ]  # fmt: skip
    try:
        yield address
    finally:
        close_clients()
        for process in processes:
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
        files.close()


def test_a_worker_killed_mid_run_does_not_fail_it(dask_cluster: str, tmp_path: Path) -> None:
    """Tiles of the sample survey on a real scheduler with two real workers; when the first
    tile is done, the worker busy with another tile is killed (SIGKILL). Dask runs its tile
    again elsewhere; the run finishes with the labels of a run in this process."""
    survey = open_survey(ROOT / "data_samples" / "urban-60m", "sim")
    pipeline = PhantomPipeline(model_path=ROOT / "models" / "phantom" / "phantom_cnn.pt")
    settings = Settings(data_dir=tmp_path, dask_scheduler=dask_cluster, sample_dir="")
    client = tile_client(settings)
    client.wait_for_workers(2, timeout=60)
    killed: list[int] = []

    def kill_a_busy_worker(stage: str, fraction: float) -> None:
        if killed or fraction == 0.0:
            return
        busy = [address for address, tasks in client.processing().items() if tasks]
        if busy:
            pids = client.run(os.getpid, workers=busy[:1])
            pid = next(iter(pids.values()))
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    there = run_phantom_tiled(
        pipeline, survey, tmp_path / "there", length=12.0, map_tiles=tile_map(settings),
        progress=kill_a_busy_worker,
    )  # fmt: skip
    assert killed, "no worker was busy when the first tile finished"
    here = run_phantom_tiled(pipeline, survey, tmp_path / "here", length=12.0)
    # 5 tiles of 12 m here, 4 evened over the 2 workers there
    assert here.index.count == 5 and there.index.count == 4
    assert there.tiles_run == there.index.count
    for frame in survey.frames:
        name = f"{frame.frame_id}.npy"
        assert np.array_equal(
            np.load(tmp_path / "here" / "labels" / name),
            np.load(tmp_path / "there" / "labels" / name),
        )


def test_a_cancelled_run_cancels_its_tiles_on_the_cluster(tmp_path: Path) -> None:
    """A job's cancel is raised from its progress callback: the tiles still queued or running
    on the cluster are cancelled, and the scheduler is left with nothing of the run."""
    survey = open_survey(ROOT / "data_samples" / "urban-60m", "sim")
    pipeline = PhantomPipeline(model_path=ROOT / "models" / "phantom" / "phantom_cnn.pt")
    settings = Settings(data_dir=tmp_path, workers=2, sample_dir="")

    class CancelRequestError(Exception):
        pass

    def cancel_after_the_first_tile(stage: str, fraction: float) -> None:
        if fraction > 0:
            raise CancelRequestError

    try:
        client = tile_client(settings)
        with pytest.raises(CancelRequestError):
            run_phantom_tiled(
                pipeline, survey, tmp_path / "run", length=12.0, map_tiles=tile_map(settings),
                progress=cancel_after_the_first_tile,
            )  # fmt: skip
        deadline = time.monotonic() + 30
        left = -1
        while time.monotonic() < deadline:
            left = client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks))
            if left == 0:
                break
            time.sleep(0.2)
        assert left == 0
        done = list((tmp_path / "run" / "tiles").glob("[0-9]" * 5 + ".json"))
        assert 1 <= len(done) < 5
    finally:
        close_clients()


def test_the_local_clusters_dashboard_listens_on_loopback_only(tmp_path: Path) -> None:
    """Admins reach the tile workers' Dask dashboard through a tunnel: it is served (bokeh is
    installed) and bound to 127.0.0.1, never to the network."""
    import httpx

    from app.jobs.cluster import close_cluster, embedded_cluster

    cluster = embedded_cluster(Settings(data_dir=tmp_path, workers=1, sample_dir=""))
    try:
        link = cluster.dashboard_link
        assert link.startswith("http://127.0.0.1:")
        assert httpx.get(link, timeout=30).status_code == 200
    finally:
        close_cluster(cluster)
