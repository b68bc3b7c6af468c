"""`mmsclean run clutter` follows the command-line contract of DESIGN.md, on simulated and real
surveys, and the pipeline removes what it should on a simulated street (synthetic)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import laspy
import numpy as np
import pytest

from app.core.labels import MOVABLE_IDS
from app.io import open_survey
from app.io.asprs import CLUTTER_LABEL_TO_ASPRS, to_asprs
from app.io.survey import Frame, Survey
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.evaluation.removal_metrics import removal_metrics
from app.pipelines.clutter.pipeline import ClutterPipeline, camera_sees_scans
from app.pipelines.clutter.run import run_clutter_to_folder
from app.simulate.survey import SimulationConfig, simulate
from tests.cli import mmsclean


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("clutter") / "sim"
    # a spinning scanner like KITTI's: the camera sees the points of its own frame (a profile
    # scanner's frame lies beside the vehicle, behind the camera)
    simulate(SimulationConfig(scene="urban", length=12.0, seed=3, scanner="hdl64"), out)
    return out


def first_frames(survey: Survey, n: int) -> Survey:
    return replace(survey, frames=list(survey.frames)[:n])


def check_contract(out: Path, survey: Survey, report: dict) -> None:
    total = 0
    for frame in survey.frames:
        labels = np.load(out / "labels" / f"{frame.frame_id}.npy")
        assert labels.dtype == np.uint8
        assert len(labels) == len(frame.points())
        assert set(np.unique(labels)) <= {0, 1}
        total += len(labels)
    removed = sum(int(np.load(out / "labels" / f"{f.frame_id}.npy").sum()) for f in survey.frames)
    cleaned = laspy.read(out / "cleaned.laz")
    gone = laspy.read(out / "removed.laz")
    assert len(cleaned.points) == total - removed and len(gone.points) == removed
    for las in (cleaned, gone):  # ASPRS classes as app.io.asprs maps the labels
        labels = np.asarray(las.mmsclean_label)
        assert np.array_equal(las.classification, to_asprs(labels, CLUTTER_LABEL_TO_ASPRS))
    assert report["counts"]["points"] == total
    assert json.loads((out / "report.json").read_text())["counts"] == report["counts"]


def test_run_clutter_cli_on_a_simulated_survey(sim_dir: Path, weights_dir: Path, tmp_path: Path):
    out = tmp_path / "out"
    result = mmsclean(
        "run",
        "clutter",
        str(sim_dir),
        "--format",
        "sim",
        "--out",
        str(out),
        "--mode",
        "dynamic",
        "--overlays",
        "1",
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    survey = open_survey(sim_dir, "sim")
    check_contract(out, survey, report)
    assert report["config"]["mode"] == "dynamic"
    assert {"in_view", "full"} <= set(report["metrics"])
    overlay = cv2.imread(str(out / "overlays" / f"{survey.frames[0].frame_id}.png"))
    assert overlay is not None and overlay.shape[:2] == (375, 1242)


def reference_class_maps(sim_dir: Path):
    """The simulator's per-pixel classes as a perfect segmenter (tests the rest of the pipeline)."""
    clutter_code = np.zeros(65536, np.uint8)
    clutter_code[MOVABLE_IDS] = 3

    def class_map(frame: Frame) -> np.ndarray:
        path = sim_dir / "ground_truth" / "masks" / f"{frame.frame_id}_semantic.png"
        return clutter_code[cv2.imread(str(path), cv2.IMREAD_UNCHANGED)]

    return class_map


def test_pipeline_on_a_simulated_street_with_reference_masks(sim_dir: Path) -> None:
    """Synthetic: perfect masks, so this checks projection, expansion, free space and tracking."""
    survey = first_frames(open_survey(sim_dir, "sim"), 8)
    refs = [f.reference_labels() for f in survey.frames]
    semantic = np.concatenate([r["semantic"] for r in refs])
    moving = np.concatenate([r["moving"] for r in refs])
    scores = {}
    for mode in ("dynamic", "clutter"):
        pipeline = ClutterPipeline(ClutterConfig(mode=mode), reference_class_maps(sim_dir))
        result = pipeline.run(survey)
        scores[mode] = removal_metrics(
            semantic, np.concatenate(result.removed), np.concatenate(result.in_view), moving
        )
    dynamic = scores["dynamic"]["full"]["dynamic"]["scores"]
    assert dynamic["SA"] > 93 and dynamic["DA"] > 90, dynamic
    clutter = scores["clutter"]["in_view"]["clutter"]["error_matrix"]
    assert clutter["clutter_omission"] < 10 and clutter["overall_accuracy"] > 90, clutter
    # parked cars stay in dynamic mode and go in clutter mode
    assert (
        scores["clutter"]["full"]["clutter"]["scores"]["DA"]
        > scores["dynamic"]["full"]["clutter"]["scores"]["DA"] + 10
    )


@pytest.mark.real_data
def test_run_clutter_on_real_semantickitti(real_data: Path, weights_dir: Path, tmp_path: Path):
    survey = first_frames(
        open_survey(real_data / "semantickitti" / "sequences" / "08", "semantickitti"), 3
    )
    report = run_clutter_to_folder(survey, tmp_path / "out", ClutterConfig(mode="clutter"))
    check_contract(tmp_path / "out", survey, report)
    view = report["metrics"]["in_view"]["clutter"]["error_matrix"]
    # real cars in the camera view: most of their points go, most of the map stays
    assert view["clutter_omission"] < 30 and view["overall_accuracy"] > 90, view


@pytest.mark.real_data
def test_run_clutter_on_real_kitti_raw(real_data: Path, weights_dir: Path, tmp_path: Path):
    drive = real_data / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_00xx_sync"
    survey = first_frames(open_survey(drive, "kitti-raw"), 3)
    report = run_clutter_to_folder(survey, tmp_path / "out", ClutterConfig(mode="clutter"))
    check_contract(tmp_path / "out", survey, report)
    assert report["counts"]["removed_points"] > 1000  # a dense traffic scene: cars are removed
    assert "metrics" not in report  # no reference labels in KITTI raw


def test_bad_mode_is_one_clear_line(tmp_path: Path) -> None:
    result = mmsclean(
        "run",
        "clutter",
        str(tmp_path),
        "--format",
        "sim",
        "--out",
        str(tmp_path / "out"),
        "--mode",
        "sometimes",
        timeout=120,
    )
    assert result.returncode != 0
    assert "--mode" in result.stderr and "sometimes" in result.stderr
    assert not (tmp_path / "out").exists()


def test_a_camera_that_never_sees_the_scans_needs_no_weights(sim_dir: Path, tmp_path: Path):
    """The sample survey's profile scanner scans beside and behind its forward camera: no mask
    could apply, so `run clutter` runs on free space and tracking without the segmentation
    weights (it stopped with "weights are missing", issue 20); a spinning scanner's survey is
    seen by its camera and still needs them."""
    sample = Path(__file__).resolve().parents[3] / "data_samples" / "urban-60m"
    profile = open_survey(sample, "sim")
    camera = next(iter(profile.cameras.values()))
    assert any(camera.name in f.image_paths for f in profile.frames)
    assert not camera_sees_scans(profile, camera)
    spinning = open_survey(sim_dir, "sim")
    assert camera_sees_scans(spinning, next(iter(spinning.cameras.values())))
    no_weights = tmp_path / "no-weights"
    no_weights.mkdir()
    env = {"MMSCLEAN_WEIGHTS_DIR": str(no_weights), "MMSCLEAN_DATA_DIR": str(tmp_path / "var")}
    out = tmp_path / "out"
    result = mmsclean(
        "run", "clutter", str(sample), "--format", "sim", "--out", str(out), env=env
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["segmenter"] is None and report["counts"]["removed_points"] > 0
    refused = mmsclean(
        "run", "clutter", str(sim_dir), "--format", "sim", "--out", str(tmp_path / "o2"), env=env
    )  # fmt: skip
    assert refused.returncode != 0 and "weights are missing" in refused.stderr
