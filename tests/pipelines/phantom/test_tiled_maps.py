"""A map file from another tool (LAS, no trajectory) runs tile by tile too: its trajectory is
traced from its points, it is read a chunk at a time, and the labels are those of the run on
the whole map."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.io import las as las_module
from app.io import open_survey
from app.io.las import write_laz
from app.io.map_trajectory import map_trajectory
from app.pipelines.phantom.pipeline import PhantomPipeline
from app.pipelines.phantom.tiled import run_phantom_tiled

ROOT = Path(__file__).resolve().parents[3]
SAMPLE = ROOT / "data_samples" / "urban-60m"
PROFILE_MODEL = ROOT / "models" / "phantom" / "phantom_cnn.pt"


def sample_map(tmp_path: Path, frames: int, with_time: bool) -> tuple[Path, np.ndarray]:
    """The sample survey's first frames as one LAS map (with their GPS times or none), and the
    sensor positions of those frames."""
    survey = open_survey(SAMPLE, "sim")
    clouds = [f.world_points() for f in survey.frames[:frames]]
    xyz = np.concatenate([c.xyz for c in clouds])
    times = np.concatenate([c.time for c in clouds]) + 1e5 if with_time else None
    path = tmp_path / "map.laz"
    write_laz(path, xyz, gps_time=times)
    return path, np.stack([f.pose[:3, 3] for f in survey.frames[:frames]])


@pytest.mark.parametrize("with_time", [True, False])
def test_a_maps_trajectory_follows_the_drive(tmp_path: Path, with_time: bool) -> None:
    path, sensor = sample_map(tmp_path, 36, with_time)
    positions, time0 = map_trajectory(open_survey(path, "las"))
    assert (time0 is not None) == with_time
    # every traced position lies near the drive, and the trace spans most of it
    gaps = np.linalg.norm(positions[:, None, :2] - sensor[None, :, :2], axis=2).min(axis=1)
    assert gaps.max() < 8.0
    drive = np.linalg.norm(sensor[-1, :2] - sensor[0, :2])
    assert np.linalg.norm(positions[-1, :2] - positions[0, :2]) > 0.6 * drive


def test_a_las_map_in_tiles_and_chunks_agrees_with_the_whole_map(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path, _ = sample_map(tmp_path, 36, with_time=True)
    monkeypatch.setattr(las_module, "_CHUNK", 100_000)  # many chunks per tile
    survey = open_survey(path, "las")
    pipeline = PhantomPipeline(model_path=PROFILE_MODEL)
    whole = pipeline.run(survey).frame_labels()["map"]
    run = run_phantom_tiled(pipeline, survey, tmp_path / "run", length=12.0)
    tiled = np.load(tmp_path / "run" / "labels" / "map.npy")
    assert run.index.count >= 3 and run.index.time0 is not None
    assert len(tiled) == len(whole) == run.counts["points"]
    assert (tiled == whole).mean() >= 0.999
    assert (tiled == 3).sum() > 1000
