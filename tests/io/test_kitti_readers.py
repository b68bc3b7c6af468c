"""KITTI raw and SemanticKITTI readers on small synthetic folders: structure and bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.core.errors import InputError, UnknownFormatError
from app.io import open_survey
from app.io.oxts import imu_poses, mercator_scale
from tests.io.kitti_fixtures import make_kitti_raw, make_semantickitti


def test_semantickitti_frames_poses_labels(tmp_path: Path) -> None:
    survey = open_survey(make_semantickitti(tmp_path / "seq"), "semantickitti")
    assert len(survey) == 3
    assert survey.reference_label_kinds == ("semantic", "instance")
    assert survey.frames[2].pose[0, 3] == pytest.approx(2.0)
    assert survey.frames[1].timestamp == pytest.approx(0.1)
    labels = survey.frames[0].reference_labels()
    assert (labels["semantic"] == 40).all() and (labels["instance"] == 7).all()
    assert survey.frames[0].points().xyz.dtype == np.float64


def test_frames_are_lazy(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    survey = open_survey(root, "semantickitti")
    (root / "velodyne" / "000001.bin").write_bytes(b"\0" * 16 * 5)  # changed after opening
    assert len(survey.frames[1].points()) == 5


def test_truncated_bin_names_the_file(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    bad = root / "velodyne" / "000001.bin"
    bad.write_bytes(bad.read_bytes()[:-3])
    with pytest.raises(
        InputError, match=r"000001\.bin: truncated: \d+ bytes is not a multiple of 16"
    ):
        open_survey(root, "semantickitti")


def test_nan_coordinates_name_the_file(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    pts = np.fromfile(root / "velodyne" / "000000.bin", dtype=np.float32).reshape(-1, 4)
    pts[[3, 9], 1] = np.nan
    pts[5, 2] = np.inf
    pts.tofile(root / "velodyne" / "000000.bin")
    survey = open_survey(root, "semantickitti")
    with pytest.raises(InputError, match=r"000000\.bin: has 3 points with NaN or infinite"):
        survey.frames[0].points()


def test_calibration_with_wrong_value_count(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    text = (root / "calib.txt").read_text().replace("Tr: 1 0 0 0", "Tr: 1 0 0")
    (root / "calib.txt").write_text(text)
    with pytest.raises(
        InputError, match=r"calib\.txt: calibration entry Tr has 11 values, expected 12"
    ):
        open_survey(root, "semantickitti")


def test_missing_calibration(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    (root / "calib.txt").unlink()
    with pytest.raises(InputError, match=r"calib\.txt: calibration file is missing"):
        open_survey(root, "semantickitti")


def test_fewer_poses_than_frames(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq", frames=3, poses=2)
    with pytest.raises(InputError, match=r"poses\.txt: has 2 poses, fewer than the frames"):
        open_survey(root, "semantickitti")


def test_label_count_mismatch(tmp_path: Path) -> None:
    root = make_semantickitti(tmp_path / "seq")
    np.zeros(7, dtype=np.uint32).tofile(root / "labels" / "000002.label")
    survey = open_survey(root, "semantickitti")
    with pytest.raises(InputError, match=r"000002\.label: has 7 labels for 100 points"):
        survey.frames[2].reference_labels()


def test_unknown_format_and_missing_source(tmp_path: Path) -> None:
    with pytest.raises(UnknownFormatError, match="unknown format 'xyz'"):
        open_survey(tmp_path, "xyz")
    with pytest.raises(InputError, match="does not exist"):
        open_survey(tmp_path / "nope", "semantickitti")


def test_kitti_raw_with_oxts(tmp_path: Path) -> None:
    sync = make_kitti_raw(tmp_path)
    for source in (sync, sync.parent):  # the sync folder or the date folder holding it
        survey = open_survey(source, "kitti-raw")
        assert len(survey) == 3 and not survey.poses_estimated
        assert survey.frames[0].pose[:3, 3] == pytest.approx([0, 0, 0])
        step = survey.frames[1].pose[:3, 3] - survey.frames[0].pose[:3, 3]
        # 1e-5 degree of longitude at 49 deg latitude, devkit Mercator: scale * lon * pi * R / 180
        expected = mercator_scale(49.0) * np.deg2rad(1e-5) * 6378137.0
        assert step[0] == pytest.approx(expected, rel=1e-6) and abs(step[1]) < 1e-6
        assert survey.frames[1].timestamp - survey.frames[0].timestamp == pytest.approx(
            1.0, abs=1e-6
        )
        assert survey.cameras["image_02"].width == 1242


def test_kitti_raw_fewer_oxts_than_scans(tmp_path: Path) -> None:
    sync = make_kitti_raw(tmp_path, frames=3, oxts=2)
    with pytest.raises(InputError, match=r"oxts/data: has 2 OXTS packets for 3 scans"):
        open_survey(sync, "kitti-raw")


def test_kitti_raw_bad_oxts_packet(tmp_path: Path) -> None:
    sync = make_kitti_raw(tmp_path)
    (sync / "oxts" / "data" / "0000000001.txt").write_text("49.0 8.4 110")
    with pytest.raises(InputError, match=r"0000000001\.txt: OXTS packet has 3 values, expected 30"):
        open_survey(sync, "kitti-raw")


def test_imu_poses_heading() -> None:
    packets = np.zeros((2, 30))
    packets[:, 0], packets[:, 1] = 49.0, 8.4
    packets[1, 5] = np.pi / 2  # yaw: facing north
    poses = imu_poses(packets)
    assert poses[1, :3, 0] == pytest.approx([0, 1, 0], abs=1e-12)  # x axis (forward) points north


def test_kitti_raw_point_times_from_sweep(tmp_path: Path) -> None:
    sync = make_kitti_raw(tmp_path)
    velo = sync / "velodyne_points"
    starts = [f"2011-09-26 13:02:2{i}.000000000" for i in range(3)]
    ends = [f"2011-09-26 13:02:2{i}.100000000" for i in range(3)]
    (velo / "timestamps_start.txt").write_text("\n".join(starts) + "\n")
    (velo / "timestamps_end.txt").write_text("\n".join(ends) + "\n")
    scan = np.array([[10, 0, 0, 0], [0, -10, 0, 0], [-10, 1e-9, 0, 0]], dtype=np.float32)
    scan.tofile(velo / "data" / "0000000001.bin")
    cloud = open_survey(sync, "kitti-raw").frames[1].points()
    start = cloud.time.min() - (cloud.time.min() % 1.0)  # whole second of frame 1's sweep
    # clockwise sweep from behind: forward at half time, right side (y < 0) at three quarters
    assert cloud.time - start == pytest.approx([0.05, 0.075, 0.0], abs=1e-6)


def test_kitti_raw_without_sweep_times_has_no_point_times(tmp_path: Path) -> None:
    assert open_survey(make_kitti_raw(tmp_path), "kitti-raw").frames[0].points().time is None
