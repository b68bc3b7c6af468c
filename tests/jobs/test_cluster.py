"""Tiles on a real Dask cluster: a local cluster of two worker processes runs the phantom
pipeline's tiles, and the labels are those of the tiles run in this process."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.core.settings import Settings
from app.io import open_survey
from app.jobs.cluster import close_clients, tile_client, tile_map
from app.pipelines.phantom.pipeline import PhantomPipeline
from app.pipelines.phantom.tiled import run_phantom_tiled

ROOT = Path(__file__).resolve().parents[2]


def test_a_local_cluster_runs_the_tiles(tmp_path: Path) -> None:
    survey = open_survey(ROOT / "data_samples" / "urban-60m", "sim")
    pipeline = PhantomPipeline(model_path=ROOT / "models" / "phantom" / "phantom_cnn.pt")
    here = run_phantom_tiled(pipeline, survey, tmp_path / "here", length=25.0)
    settings = Settings(data_dir=tmp_path, workers=2, sample_dir="")
    try:
        client = tile_client(settings)
        assert len(client.scheduler_info()["workers"]) == 2
        seen = []
        run_phantom_tiled(
            pipeline, survey, tmp_path / "there", length=25.0, map_tiles=tile_map(settings),
            progress=lambda stage, fraction: seen.append(fraction),
        )  # fmt: skip
        assert tile_client(settings) is client  # one cluster per process
    finally:
        close_clients()
    assert here.index.count == 3 and seen == [0.0, 1 / 3, 2 / 3, 1.0]
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
