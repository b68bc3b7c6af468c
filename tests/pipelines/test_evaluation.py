"""`mmsclean evaluate`: contract labels scored against the reference, as the runs score them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.core.errors import InputError
from app.io import open_survey
from app.io.survey import Survey
from app.pipelines.clutter.evaluation.removal_metrics import reference_masks
from app.pipelines.evaluation import evaluate_labels, read_frame_labels
from app.pipelines.outputs import write_frame_labels
from app.pipelines.phantom.run import run_phantom_to_folder
from tests.cli import mmsclean


@pytest.fixture(scope="module")
def survey(profile_street: Path) -> Survey:
    return open_survey(profile_street, "sim")


def reference_labels(survey: Survey, pipeline: str) -> dict[str, np.ndarray]:
    """Per frame, the labels a perfect method would write."""
    out = {}
    for frame in survey.frames:
        ref = frame.reference_labels()
        if pipeline == "clutter":
            flags = reference_masks(ref["semantic"], ref["moving"])["clutter"]
        else:
            flags = ref["guardrail"] >= 0
        out[frame.frame_id] = flags.astype(np.uint8)
    return out


def test_perfect_clutter_and_guardrail_labels(survey: Survey, tmp_path: Path) -> None:
    write_frame_labels(tmp_path / "clutter", reference_labels(survey, "clutter"))
    labels = read_frame_labels(tmp_path / "clutter", survey, "clutter")
    clutter = evaluate_labels(survey, "clutter", labels)["full"]["clutter"]["error_matrix"]
    assert clutter["overall_accuracy"] == 100.0
    assert clutter["clutter_omission"] == 0.0 and clutter["map_commission"] == 0.0
    write_frame_labels(tmp_path / "guardrail", reference_labels(survey, "guardrail"))
    labels = read_frame_labels(tmp_path / "guardrail", survey, "guardrail")
    point = evaluate_labels(survey, "guardrail", labels)["point"]
    assert point["support"] > 0 and point["precision"] == point["recall"] == 100.0


def test_phantom_scores_equal_the_run_report(
    survey: Survey, random_phantom_model: Path, tmp_path: Path
) -> None:
    report = run_phantom_to_folder(survey, tmp_path / "run", model_path=random_phantom_model)
    scored = evaluate_labels(
        survey, "phantom", read_frame_labels(tmp_path / "run", survey, "phantom")
    )
    assert scored["point"] == report["metrics"]["point"]
    assert scored["phantom_points"] == report["metrics"]["phantom_points"]["mmsclean"]


def test_cli_prints_tables_and_writes_json(profile_street: Path, survey: Survey, tmp_path: Path):
    write_frame_labels(tmp_path / "run", reference_labels(survey, "clutter"))
    result = mmsclean(
        "evaluate",
        "clutter",
        str(tmp_path / "run"),
        str(profile_street),
        "--format",
        "sim",
        "--json",
        str(tmp_path / "metrics.json"),
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert "clutter removal" in result.stdout and "100.00" in result.stdout
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["pipeline"] == "clutter"
    assert written["metrics"]["full"]["clutter"]["error_matrix"]["overall_accuracy"] == 100.0


def test_bad_labels_name_the_file(survey: Survey, tmp_path: Path) -> None:
    labels = reference_labels(survey, "clutter")
    first = survey.frames[0].frame_id
    folder = tmp_path / "labels"
    write_frame_labels(tmp_path, labels)
    (folder / f"{first}.npy").unlink()
    with pytest.raises(InputError, match=f"{first}.npy.*is missing"):
        read_frame_labels(tmp_path, survey, "clutter")
    np.save(folder / f"{first}.npy", labels[first][:-1])
    with pytest.raises(InputError, match=f"{first}.npy.*points"):
        read_frame_labels(tmp_path, survey, "clutter")
    np.save(folder / f"{first}.npy", labels[first] * 3)
    with pytest.raises(InputError, match="outside 0..1"):
        read_frame_labels(tmp_path, survey, "clutter")
    assert read_frame_labels(tmp_path, survey, "phantom")  # 0..3 is fine for phantom
    np.save(folder / f"{first}.npy", labels[first].astype(np.float32))
    with pytest.raises(InputError, match="float32"):
        read_frame_labels(tmp_path, survey, "clutter")
    with pytest.raises(InputError, match="not a folder"):
        read_frame_labels(tmp_path / "nothing", survey, "clutter")


def test_no_reference_is_an_input_error(tmp_path: Path) -> None:
    """A LAS map without classification has nothing to score against: one clear error."""
    from app.io.las import write_laz

    write_laz(tmp_path / "map.laz", np.random.default_rng(0).random((100, 3)) * 10)
    survey = open_survey(tmp_path / "map.laz", "las")
    labels = [np.zeros(100, np.uint8)]
    with pytest.raises(InputError, match="no semantic reference labels"):
        evaluate_labels(survey, "clutter", labels)
