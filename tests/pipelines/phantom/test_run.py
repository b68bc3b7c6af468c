"""`mmsclean run phantom` follows the command-line contract of DESIGN.md."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
import torch

from app.io import open_survey
from app.pipelines.phantom.model import save_model
from app.pipelines.phantom.network import PillarCNN
from app.simulate.survey import SimulationConfig, simulate


@pytest.fixture(scope="module")
def survey_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("phantom") / "sim"
    simulate(
        SimulationConfig(scene="mixed", length=20.0, seed=5, scanner="profile", camera=False), out
    )
    return out


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.manual_seed(0)
    return save_model(tmp_path_factory.mktemp("model") / "net.pt", PillarCNN(), {"name": "random"})


def test_run_phantom_contract(survey_dir: Path, model: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "app",
            "run",
            "phantom",
            str(survey_dir),
            "--format",
            "sim",
            "--out",
            str(out),
            "--model",
            str(model),
            "--baselines",
        ],  # fmt: skip
        capture_output=True,
        text=True,
        env=os.environ.copy(),
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    survey = open_survey(survey_dir, "sim")
    for frame in survey.frames:
        labels = np.load(out / "labels" / f"{frame.frame_id}.npy")
        assert labels.dtype == np.uint8 and labels.shape == (frame.point_count,)
        assert labels.max() <= 3
    report = json.loads((out / "report.json").read_text())
    assert report["pipeline"] == "phantom" and report["counts"]["points"] > 0
    metrics = report["metrics"]
    for level in ("pillar", "pillar_raw", "point"):
        assert set(metrics[level]["classes"]) == {
            "ground",
            "high object",
            "short object",
            "phantom",
        }
    assert set(metrics["phantom_points"]) == {"mmsclean", "num_neighbors", "avg_distances"}
    cleaned = laspy.read(out / "cleaned.laz")
    kept = sum(
        int((np.load(out / "labels" / f"{f.frame_id}.npy") != 3).sum()) for f in survey.frames
    )
    assert len(cleaned.points) == kept
    assert (out / "confusion_pillar.png").is_file() and (out / "pillars.npz").is_file()


def test_dense_and_windows_agree_on_a_survey(survey_dir: Path, model: Path, tmp_path: Path) -> None:
    from app.pipelines.phantom.run import run_phantom_to_folder

    survey = open_survey(survey_dir, "sim")
    dense = run_phantom_to_folder(survey, tmp_path / "d", model_path=model, refine=False)
    windows = run_phantom_to_folder(
        survey, tmp_path / "w", model_path=model, dense=False, refine=False
    )
    a = np.load(tmp_path / "d" / "pillars.npz")
    b = np.load(tmp_path / "w" / "pillars.npz")
    assert np.array_equal(a["classified"], b["classified"])
    judged = a["classified"]
    assert judged.sum() > 100  # the CNN ran on the object pillars, not only on gated ground
    assert (a["labels"][judged] == b["labels"][judged]).mean() >= 0.999
    assert (a["labels"][~judged] == 0).all()
    assert dense["counts"]["pillars"] == windows["counts"]["pillars"]


def test_missing_model_is_one_line(survey_dir: Path, tmp_path: Path) -> None:
    missing = tmp_path / "none.pt"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "app",
            "run",
            "phantom",
            str(survey_dir),
            "--format",
            "sim",
            "--out",
            str(tmp_path / "o"),
            "--model",
            str(missing),
        ],  # fmt: skip
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert str(missing) in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_run_on_a_las_map(survey_dir: Path, model: Path, tmp_path: Path) -> None:
    """An accumulated map without SemanticKITTI labels: labels for frame `map`, no metrics."""
    from app.io.las import write_laz
    from app.pipelines.phantom.run import run_phantom_to_folder

    survey = open_survey(survey_dir, "sim")
    xyz = np.concatenate([f.world_points().xyz for f in survey.frames[:5]])
    las = write_laz(tmp_path / "map.laz", xyz, classification=np.full(len(xyz), 2, np.uint8))
    report = run_phantom_to_folder(open_survey(las, "las"), tmp_path / "out", model_path=model)
    labels = np.load(tmp_path / "out" / "labels" / "map.npy")
    assert labels.shape == (len(xyz),) and "metrics" not in report
