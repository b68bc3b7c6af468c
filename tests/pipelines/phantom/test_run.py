"""`mmsclean run phantom` follows the command-line contract of DESIGN.md."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np

from app.io import open_survey
from app.io.asprs import PHANTOM_LABEL_TO_ASPRS, to_asprs
from tests.cli import mmsclean


def run_phantom(survey: Path, out: Path, model: Path, *extra: str, timeout: float):
    """`mmsclean run phantom` on a simulated survey folder."""
    return mmsclean(
        "run", "phantom", str(survey), "--format", "sim", "--out", str(out),
        "--model", str(model), *extra, timeout=timeout,
    )  # fmt: skip


def test_run_phantom_contract(
    profile_street: Path, random_phantom_model: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    result = run_phantom(profile_street, out, random_phantom_model, "--baselines", timeout=600)
    assert result.returncode == 0, result.stderr
    survey = open_survey(profile_street, "sim")
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
    labels = np.asarray(cleaned.mmsclean_label)  # ASPRS classes as app.io.asprs maps the labels
    assert np.array_equal(cleaned.classification, to_asprs(labels, PHANTOM_LABEL_TO_ASPRS))
    assert (out / "confusion_pillar.png").is_file() and (out / "pillars.npz").is_file()


def test_dense_and_windows_agree_on_a_survey(
    profile_street: Path, random_phantom_model: Path, tmp_path: Path
) -> None:
    from app.pipelines.phantom.run import run_phantom_to_folder

    survey = open_survey(profile_street, "sim")
    dense = run_phantom_to_folder(
        survey, tmp_path / "d", model_path=random_phantom_model, refine=False
    )
    windows = run_phantom_to_folder(
        survey, tmp_path / "w", model_path=random_phantom_model, dense=False, refine=False
    )
    a = np.load(tmp_path / "d" / "pillars.npz")
    b = np.load(tmp_path / "w" / "pillars.npz")
    assert np.array_equal(a["classified"], b["classified"])
    judged = a["classified"]
    assert judged.sum() > 100  # the CNN ran on the object pillars, not only on gated ground
    assert (a["labels"][judged] == b["labels"][judged]).mean() >= 0.999
    assert (a["labels"][~judged] == 0).all()
    assert dense["counts"]["pillars"] == windows["counts"]["pillars"]


def test_missing_model_is_one_line(profile_street: Path, tmp_path: Path) -> None:
    missing = tmp_path / "none.pt"
    result = run_phantom(profile_street, tmp_path / "o", missing, timeout=120)
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert str(missing) in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_run_on_a_las_map(profile_street: Path, random_phantom_model: Path, tmp_path: Path) -> None:
    """An accumulated map without SemanticKITTI labels: labels for frame `map`, no metrics."""
    from app.io.las import write_laz
    from app.pipelines.phantom.run import run_phantom_to_folder

    survey = open_survey(profile_street, "sim")
    xyz = np.concatenate([f.world_points().xyz for f in survey.frames[:5]])
    las = write_laz(tmp_path / "map.laz", xyz, classification=np.full(len(xyz), 2, np.uint8))
    report = run_phantom_to_folder(
        open_survey(las, "las"), tmp_path / "out", model_path=random_phantom_model
    )
    labels = np.load(tmp_path / "out" / "labels" / "map.npy")
    assert labels.shape == (len(xyz),) and "metrics" not in report
