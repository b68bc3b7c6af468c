"""`mmsclean run` picks the model of the survey's sensor kind, or says in one line why it cannot;
a model forced by hand runs, with an off-domain warning (issue 16, part 1)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.io.las import write_laz
from tests.cli import assert_one_line_error, mmsclean


@pytest.fixture
def untimed_map(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(0, 20, (20_000, 2)), rng.normal(0, 0.02, 20_000)]
    box = np.c_[rng.uniform(5, 9, (3_000, 2)), rng.uniform(0.3, 1.5, 3_000)]
    path = tmp_path / "map.laz"
    write_laz(path, np.concatenate([ground, box]) + [500_000.0, 5_000_000.0, 100.0])
    return path


def test_a_map_of_unknown_sensor_kind_asks_for_one(untimed_map: Path, tmp_path: Path) -> None:
    result = mmsclean("run", "phantom", str(untimed_map), "-f", "las", "-o", str(tmp_path / "r"))
    assert_one_line_error(result, "sensor kind is unknown", "--sensor rotating|profile")


def test_a_declared_kind_picks_its_shipped_model(untimed_map: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = mmsclean(
        "run", "phantom", str(untimed_map), "-f", "las", "-o", str(out), "--sensor", "profile"
    )
    assert result.returncode == 0, result.stderr
    model = json.loads((out / "report.json").read_text())["model"]
    assert model["sensor_kind"] == "profile" and not model["off_domain"]
    assert model["chosen"] == "by the survey's sensor kind"
    assert "warning" not in result.stderr


def test_a_bad_sensor_value_is_named(untimed_map: Path, tmp_path: Path) -> None:
    result = mmsclean(
        "run", "phantom", str(untimed_map), "-f", "las", "-o", str(tmp_path / "r"),
        "--sensor", "lidar",
    )  # fmt: skip
    assert_one_line_error(result, "--sensor", "rotating, profile")


def test_a_forced_model_runs_and_is_flagged_off_domain(untimed_map: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    shipped = Path(__file__).resolve().parents[1] / "models/phantom/phantom_cnn_context.pt"
    result = mmsclean(
        "run", "phantom", str(untimed_map), "-f", "las", "-o", str(out),
        "--model", str(shipped), "--sensor", "rotating",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    model = json.loads((out / "report.json").read_text())["model"]
    assert model["off_domain"] and model["chosen"] == "by hand"
    assert "off-domain: a model for profile scanners ran on a rotating-scanner survey" in (
        result.stderr
    )


def test_real_rotating_data_trains_only_a_rotating_model(real_data: Path, tmp_path: Path) -> None:
    sequence = real_data / "semantickitti" / "sequences" / "05"
    result = mmsclean(
        "train", "phantom", "--semantickitti", str(sequence), "-o", str(tmp_path / "m.pt")
    )
    assert_one_line_error(result, "--semantickitti", "--sensor rotating")
    bad = mmsclean("train", "phantom", "--sensor", "lidar", "-o", str(tmp_path / "m.pt"))
    assert_one_line_error(bad, "--sensor")


def test_a_rerun_into_the_same_folder_keeps_the_finished_tiles(
    untimed_map: Path, tmp_path: Path
) -> None:
    """`run phantom` writes its tiles as they finish; run again into the same folder (after an
    interruption), it reruns only the tiles without results: here none."""
    out = tmp_path / "run"
    args = ("run", "phantom", str(untimed_map), "-f", "las", "-o", str(out), "--sensor", "profile")
    assert mmsclean(*args).returncode == 0
    first = json.loads((out / "report.json").read_text())["tiles"]
    again = mmsclean(*args)
    assert again.returncode == 0, again.stderr
    tiles = json.loads((out / "report.json").read_text())["tiles"]
    assert first["run"] == tiles["count"] >= 1 and tiles["run"] == 0
    assert tiles["kept_from_earlier_attempt"] == tiles["count"]
    bad = mmsclean(*args, "--scheduler", "file:///etc/passwd")
    assert_one_line_error(bad, "--scheduler", "not a Dask scheduler address")
