"""Readers on the real KITTI / SemanticKITTI sample (MMSCLEAN_REAL_DATA)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from app.geometry.projection import project
from app.geometry.transforms import apply
from app.io import open_survey
from app.io.images import image_size
from app.io.kitti_object import read_object_camera, read_object_labels, rectified_camera_points
from app.io.summary import summarize
from app.io.velodyne_bin import read_velodyne_bin

pytestmark = pytest.mark.real_data

# building, fence, other-structure, trunk, pole, traffic-sign: rigid, sharp structure
HARD_STRUCTURE = [50, 51, 52, 71, 80, 81]


def test_info_semantickitti_04(real_data: Path) -> None:
    s = summarize(open_survey(real_data / "semantickitti/sequences/04", "semantickitti"))
    assert s.frames == 10
    assert 1.15e6 < s.points < 1.3e6
    assert any(c.startswith("image_2 (P2, 1226x370") for c in s.cameras)
    assert s.reference_labels == ["semantic", "instance"]
    assert s.time_span_s == pytest.approx(0.9, abs=0.1)
    assert 5 < s.trajectory_length_m < 30


def test_info_kitti_raw_drive(real_data: Path) -> None:
    survey = open_survey(real_data / "kitti_raw/2011_09_26/2011_09_26_drive_00xx_sync", "kitti-raw")
    s = summarize(survey)
    assert s.frames == 20 and s.points > 1e6
    assert survey.poses_estimated and "estimated" in s.poses
    assert survey.cameras["image_02"].width == 1242
    poses = survey.poses()
    assert np.allclose(poses[0], np.eye(4))
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert (steps < 1.5).all()  # < 15 m/s between 10 Hz scans: odometry did not jump


@pytest.mark.parametrize("sequence", ["04", "05", "08"])
def test_posed_frames_align(real_data: Path, sequence: str) -> None:
    """Frame 9's rigid structure lies on frame 0's once both are posed, and not before."""
    survey = open_survey(real_data / f"semantickitti/sequences/{sequence}", "semantickitti")
    f0, f9 = survey.frames[0], survey.frames[9]

    def structure(frame):
        keep = np.isin(frame.reference_labels()["semantic"], HARD_STRUCTURE)
        return frame.points().xyz[keep]

    local0, local9 = structure(f0), structure(f9)
    world0, world9 = apply(f0.pose, local0), apply(f9.pose, local9)
    # compare where both scans sample densely: within 25 m of both sensor positions
    near = (np.linalg.norm(world9 - f0.pose[:3, 3], axis=1) < 25) & (
        np.linalg.norm(world9 - f9.pose[:3, 3], axis=1) < 25
    )
    assert near.sum() > 1000
    posed = np.median(cKDTree(world0).query(world9[near], workers=-1)[0])
    unposed = np.median(cKDTree(local0).query(local9[near], workers=-1)[0])
    assert posed < 0.10, f"posed median NN distance {posed:.3f} m"
    assert unposed > 0.5, f"unposed median NN distance {unposed:.3f} m"


@pytest.mark.parametrize("frame", ["000000", "000001", "000002"])
def test_object_boxes_project_into_2d_boxes(real_data: Path, frame: str) -> None:
    root = real_data / "kitti_object/training"
    width, height = image_size(root / f"image_2/{frame}.png")
    camera = read_object_camera(root / f"calib/{frame}.txt", width, height)
    xyz = read_velodyne_bin(root / f"velodyne/{frame}.bin").xyz
    xyz_cam = rectified_camera_points(camera, xyz)
    proj = project(xyz, camera.P, camera.T_cam_sensor, width, height)
    checked = 0
    for box in read_object_labels(root / f"label_2/{frame}.txt"):
        inside = box.contains(xyz_cam) & proj.in_image
        if inside.sum() < 20:  # occluded or far: too few points to judge
            continue
        u, v = proj.uv[inside].T
        left, top, right, bottom = box.bbox
        tol = 2.0  # pixels: 2D boxes are hand-drawn
        hit = (u >= left - tol) & (u <= right + tol) & (v >= top - tol) & (v <= bottom + tol)
        assert hit.mean() >= 0.95, f"{box.type}: {hit.mean():.1%} of its points in its 2D box"
        checked += 1
    assert checked >= 1


def test_real_oxts_packet_and_timestamps(real_data: Path) -> None:
    """The devkit's own files of drive 0001: field order, one packet, 10 Hz timestamps."""
    from app.io.kitti_raw import read_timestamps
    from app.io.oxts import OXTS_FIELDS, imu_poses, read_oxts_packet

    drive = real_data / (
        "kitti_raw/drive_0001_meta/2011_09_26_drive_0001_sync/2011_09_26/2011_09_26_drive_0001_sync"
    )
    documented = [
        ln.split(":")[0] for ln in (drive / "oxts/dataformat.txt").read_text().split("\n")
    ]
    documented = [name for name in documented if name]
    # dataformat.txt of the devkit lists "ay" twice; the 14th value is the z acceleration
    assert documented[:13] == list(OXTS_FIELDS[:13]) and documented[13] == "ay"
    assert documented[14:] == list(OXTS_FIELDS[14:])
    packet = read_oxts_packet(drive / "oxts/data/0000000000.txt")
    assert packet[0] == pytest.approx(49.015003823272)  # Karlsruhe
    pose = imu_poses(packet)[0]
    assert pose[:3, 3] == pytest.approx([0, 0, 0])
    assert np.degrees(np.arctan2(pose[1, 0], pose[0, 0])) == pytest.approx(np.degrees(packet[5]))
    times = read_timestamps(drive / "velodyne_points/timestamps.txt", 108)
    starts = read_timestamps(drive / "velodyne_points/timestamps_start.txt", 108)
    ends = read_timestamps(drive / "velodyne_points/timestamps_end.txt", 108)
    assert np.diff(times) == pytest.approx(0.1, abs=0.01)
    assert (starts < times).all() and (times < ends).all()
