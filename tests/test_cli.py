"""The `mmsclean` command as a user runs it: one-line errors, exit codes, the info summary."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.cli import assert_one_line_error, mmsclean
from tests.io.kitti_fixtures import make_semantickitti


def test_info_json(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq", frames=4)
    result = mmsclean("info", str(root), "--format", "semantickitti", "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["frames"] == 4 and summary["points"] == 400
    assert summary["reference_labels"] == ["semantic", "instance"]
    assert summary["trajectory_length_m"] == pytest.approx(3.0)


def test_info_table(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq", frames=2)
    result = mmsclean("info", str(root), "-f", "semantickitti")
    assert result.returncode == 0, result.stderr
    assert "frames" in result.stdout and "reference labels" in result.stdout


def test_unknown_format(tmp_path: Path) -> None:
    assert_one_line_error(mmsclean("info", str(tmp_path), "-f", "e57"), "unknown format 'e57'")


def test_missing_source(tmp_path: Path) -> None:
    missing = tmp_path / "nothing-here"
    assert_one_line_error(
        mmsclean("info", str(missing), "-f", "las"), str(missing), "does not exist"
    )


def test_truncated_scan(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    scan = root / "velodyne" / "000002.bin"
    scan.write_bytes(scan.read_bytes()[:-5])
    assert_one_line_error(
        mmsclean("info", str(root), "-f", "semantickitti"), "000002.bin", "truncated"
    )


def test_nan_coordinates_found_by_check(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    scan = root / "velodyne" / "000001.bin"
    points = np.fromfile(scan, dtype=np.float32).reshape(-1, 4)
    points[10, 0] = np.nan
    points.tofile(scan)
    assert_one_line_error(
        mmsclean("info", str(root), "-f", "semantickitti", "--check"),
        "000001.bin",
        "has 1 points with NaN or infinite coordinates",
    )


def test_check_reports_world_bounds(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq", frames=2)
    result = mmsclean("info", str(root), "-f", "semantickitti", "--check", "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["points"] == 200
    assert summary["bounds_max"][0] > summary["bounds_min"][0]


def test_malformed_calibration(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    (root / "calib.txt").write_text("P2: 1 2 3\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    assert_one_line_error(
        mmsclean("info", str(root), "-f", "semantickitti"), "calib.txt", "P2 has 3 values"
    )


def test_fewer_poses_than_frames(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq", frames=4, poses=3)
    assert_one_line_error(
        mmsclean("info", str(root), "-f", "semantickitti"), "poses.txt", "fewer than the frames"
    )


def test_empty_las(tmp_path: Path) -> None:
    import laspy

    path = tmp_path / "empty.las"
    laspy.create(point_format=6, file_version="1.4").write(path)
    assert_one_line_error(mmsclean("info", str(path), "-f", "las"), "empty.las", "no points")


def test_usage_error_is_not_a_traceback() -> None:
    result = mmsclean("info")
    assert result.returncode != 0 and "Traceback" not in result.stderr


@pytest.mark.real_data
def test_info_real_semantickitti(real_data: Path) -> None:
    result = mmsclean(
        "info", str(real_data / "semantickitti/sequences/04"), "-f", "semantickitti", "--json"
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["frames"] == 10 and 1.15e6 < summary["points"] < 1.3e6
    assert summary["reference_labels"] and summary["cameras"][0].startswith("image_2")
    assert summary["sensor_kind"] == "rotating"


@pytest.mark.real_data
def test_info_real_kitti_raw(real_data: Path) -> None:
    drive = real_data / "kitti_raw/2011_09_26/2011_09_26_drive_00xx_sync"
    result = mmsclean("info", str(drive), "-f", "kitti-raw", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["frames"] == 20


@pytest.mark.parametrize(
    ("option", "value", "problem"),
    [
        ("--dufomap-resolution", "0.001", "greater than or equal to 0.02"),
        ("--dufomap-resolution", "nan", "finite number"),
        ("--padding", "1000000000", "less than or equal to 200"),
        ("--threads", "1000000", "less than or equal to 256"),
        ("--voxel-dedup", "inf", "finite number"),
        ("--image-gamma", "5", "less than or equal to 2"),
    ],
)
def test_run_clutter_options_are_bounded(
    tmp_path: Path, option: str, value: str, problem: str
) -> None:
    """The command line builds the job's config model: the same bounds, one line, exit 2."""
    root = make_semantickitti(tmp_path / "seq", frames=2)
    result = mmsclean(
        "run", "clutter", str(root), "-f", "semantickitti", "--out", str(tmp_path / "out"),
        option, value,
    )  # fmt: skip
    assert_one_line_error(result, f"{option}: Input should be", problem, "(got ")
    assert result.returncode == 2
    assert not (tmp_path / "out").exists()


def test_train_phantom_options_are_bounded(tmp_path: Path) -> None:
    result = mmsclean(
        "train", "phantom", "--out", str(tmp_path / "m.pt"), "--per-class", "1000000000"
    )
    assert_one_line_error(result, "--per-class: Input should be less than or equal to 1000000")
    assert not (tmp_path / "m.pt").exists()


def test_train_clutter_shapes_learns_from_simulated_and_real_streets(
    tmp_path: Path, real_data: Path
) -> None:
    """One simulated street per set, with hedges and bushes, and a real labelled sequence: the
    checkpoint's card says what it learnt from."""
    out = tmp_path / "shapes.pt"
    sequence = real_data / "semantickitti" / "sequences" / "05"
    result = mmsclean(
        "train", "clutter-shapes", "--out", str(out), "--sim-seeds", "1", "--validation-seeds",
        "2", "--epochs", "1", "--scenes", "urban", "--vegetation", "--semantickitti",
        str(sequence), "--real-weight", "5",
        env={"MMSCLEAN_DATA_DIR": str(tmp_path / "data")},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["simulation"]["scenes"] == ["urban"] and card["simulation"]["vegetation"]
    assert card["real"]["sequences"] == ["05"] and card["real"]["weight"] == 5.0
    assert card["real"]["vehicles"] > 0 and card["validation"]["samples"] > 0


def test_train_clutter_shapes_names_a_bad_option(tmp_path: Path) -> None:
    out = str(tmp_path / "shapes.pt")
    not_a_sequence = tmp_path / "nothing"
    not_a_sequence.mkdir()
    result = mmsclean(
        "train", "clutter-shapes", "--out", out, "--semantickitti", str(not_a_sequence)
    )
    assert_one_line_error(result, "--semantickitti", "is not a labelled SemanticKITTI sequence")
    result = mmsclean("train", "clutter-shapes", "--out", out, "--scenes", "urban,forest")
    assert_one_line_error(result, "--scenes", "forest")
    assert not (tmp_path / "shapes.pt").exists()


def test_simulate_a_street_with_hedges_and_bushes(tmp_path: Path) -> None:
    out = tmp_path / "street"
    result = mmsclean(
        "simulate", "--out", str(out), "--length", "10", "--seed", "1", "--no-camera",
        "--vegetation",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    objects = json.loads((out / "ground_truth" / "scene.json").read_text())["objects"]
    assert {"hedge", "bush"} & {o["name"] for o in objects}
