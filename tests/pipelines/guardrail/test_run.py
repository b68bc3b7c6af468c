"""`mmsclean run guardrail` follows the command-line contract of DESIGN.md and finds the
simulated guardrails with the shipped classifier (synthetic)."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest
import trimesh

from app.io import open_survey
from app.simulate.survey import SimulationConfig, simulate
from tests.cli import mmsclean


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("guardrail") / "sim"
    # seed 7 is in none of the classifier's training, validation or held-out sets
    simulate(SimulationConfig(scene="urban", length=30.0, seed=7, scanner="profile"), out)
    return out


def test_run_guardrail_cli_on_a_simulated_street(sim_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = mmsclean(
        "run",
        "guardrail",
        str(sim_dir),
        "--format",
        "sim",
        "--out",
        str(out),
        "--tile-length",
        "20",
        timeout=900,
    )
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["tiles"]["count"] == 2  # 30 m in 20 m tiles: the image head over both
    survey = open_survey(sim_dir, "sim")
    total = 0
    for frame in survey.frames:
        labels = np.load(out / "labels" / f"{frame.frame_id}.npy")
        assert labels.dtype == np.uint8 and len(labels) == len(frame.points())
        assert set(np.unique(labels)) <= {0, 1}
        total += int(labels.sum())
    assert total == report["counts"]["guardrail_points"] > 0
    assert len(laspy.read(out / "guardrail_points.laz").points) == total
    # the shipped classifier finds the pipe and the beam guardrail of the urban street
    slices = report["metrics"]["slice"]
    assert slices["precision"] > 80 and slices["recall"] > 80, slices
    modelled = [g for g in report["guardrails"] if "files" in g]
    assert modelled, report["guardrails"]
    for g in modelled:
        mesh = trimesh.load(out / g["files"]["ply"], force="mesh")
        assert len(mesh.faces) > 0
        assert (out / g["files"]["glb"]).is_file() and (out / g["files"]["obj"]).is_file()


def test_bad_head_is_one_clear_line(tmp_path: Path) -> None:
    result = mmsclean(
        "run",
        "guardrail",
        str(tmp_path),
        "--format",
        "sim",
        "--out",
        str(tmp_path / "out"),
        "--head",
        "colour",
        timeout=120,
    )
    assert result.returncode != 0
    assert "--head" in result.stderr and "colour" in result.stderr
    assert not (tmp_path / "out").exists()
