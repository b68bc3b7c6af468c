"""Write a simulated survey as a KITTI-raw-like folder plus its ground truth.

    OUT/calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt
    OUT/velodyne_points/data/NNNNNNNNNN.bin   float32 x y z reflectance, sensor frame
    OUT/velodyne_points/timestamps.txt, timestamps_start.txt, timestamps_end.txt
    OUT/image_02/data/NNNNNNNNNN.png          RGB render at the frame's reference time
    OUT/oxts/data/NNNNNNNNNN.txt              GNSS/INS packets (devkit Mercator convention)
    OUT/poses.txt                             sensor -> world per frame (as measured)
    OUT/trajectory.txt                        time + sensor -> world at the scanner's rate
    OUT/ground_truth/...                      labels per point, masks, poses, scene, guardrails

The `kitti-raw` reader reads the sensor part (poses from the OXTS packets, relative to the first
fix); the `sim` reader adds the exact world poses and the ground truth.
Every file is written deterministically: same simulation -> same bytes.
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path

import cv2
import numpy as np

from app.io.kitti_raw import LAZ_INTENSITY_SCALE
from app.io.las import write_laz
from app.io.oxts import EARTH_RADIUS_M, OXTS_FIELD_COUNT, mercator_scale

TIME_BASE = np.datetime64("2020-06-01T10:00:00", "ns")  # simulation time 0 as a wall-clock time
FIXED_DATE = (2020, 6, 1)  # creation date written into LAZ files: same bytes on every run
PNG_OPTIONS = [cv2.IMWRITE_PNG_COMPRESSION, 6]  # near the smallest files at 1/5 the time of 9
GEO_ORIGIN = (49.0, 8.4)  # latitude, longitude (degrees) of the first GNSS fix


def frame_name(index: int) -> str:
    return f"{index:010d}"


def format_timestamps(times: np.ndarray) -> str:
    """KITTI `timestamps.txt` lines (YYYY-MM-DD hh:mm:ss.fffffffff) for simulation seconds."""
    stamps = TIME_BASE + np.round(np.asarray(times) * 1e9).astype("timedelta64[ns]")
    return "".join(str(s).replace("T", " ") + "\n" for s in stamps)


def write_json(path: Path, payload: object) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=1, sort_keys=True) + "\n")


def matrix_line(values: np.ndarray) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(values, dtype=np.float64).ravel())


def write_calibration(
    out: Path,
    P: np.ndarray,
    width: int,
    height: int,
    T_cam_velo: np.ndarray,
    T_velo_imu: np.ndarray,
) -> None:
    """The three KITTI raw calibration files for camera 02 (rectified, identity R_rect)."""
    (out / "calib_cam_to_cam.txt").write_text(
        "calib_time: simulated\n"
        f"S_rect_02: {width:.6e} {height:.6e}\n"
        f"R_rect_00: {matrix_line(np.eye(3))}\n"
        f"P_rect_02: {matrix_line(P)}\n"
    )
    for name, T in (("calib_velo_to_cam.txt", T_cam_velo), ("calib_imu_to_velo.txt", T_velo_imu)):
        (out / name).write_text(
            f"calib_time: simulated\nR: {matrix_line(T[:3, :3])}\nT: {matrix_line(T[:3, 3])}\n"
        )


def oxts_packets(T_world_imu: np.ndarray, speeds: np.ndarray) -> np.ndarray:
    """(F, 30) OXTS packets whose devkit poses (relative to the first fix) equal the given IMU
    poses minus the first position: latitude/longitude by inverting the Mercator projection
    with the scale of the first fix, which sits at GEO_ORIGIN."""
    lat0, lon0 = GEO_ORIGIN
    scale = mercator_scale(lat0)
    mx0 = scale * np.deg2rad(lon0) * EARTH_RADIUS_M
    my0 = scale * EARTH_RADIUS_M * np.log(np.tan(np.deg2rad(90.0 + lat0) / 2.0))
    t = T_world_imu[:, :3, 3] - T_world_imu[0, :3, 3]
    mx, my = mx0 + t[:, 0], my0 + t[:, 1]
    lon = np.rad2deg(mx / (scale * EARTH_RADIUS_M))
    lat = np.rad2deg(2.0 * np.arctan(np.exp(my / (scale * EARTH_RADIUS_M)))) - 90.0
    R = T_world_imu[:, :3, :3]
    # R = Rz(yaw) Ry(pitch) Rx(roll)
    pitch = -np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    packets = np.zeros((len(R), OXTS_FIELD_COUNT))
    packets[:, 0], packets[:, 1], packets[:, 2] = lat, lon, 100.0 + T_world_imu[:, 2, 3]
    packets[:, 3], packets[:, 4], packets[:, 5] = roll, pitch, yaw
    packets[:, 6] = speeds * np.sin(yaw)  # vn
    packets[:, 7] = speeds * np.cos(yaw)  # ve
    packets[:, 8] = speeds  # vf
    packets[:, 25:30] = [4, 10, 5, 5, 6]  # navstat, numsats, posmode, velmode, orimode
    return packets


def write_oxts(out: Path, packets: np.ndarray, times: np.ndarray) -> None:
    folder = out / "oxts" / "data"
    folder.mkdir(parents=True, exist_ok=True)
    for i, packet in enumerate(packets):
        line = " ".join(f"{v:.12f}" if k < 6 else f"{v:.9g}" for k, v in enumerate(packet))
        (folder / f"{frame_name(i)}.txt").write_text(line + "\n")
    (out / "oxts" / "timestamps.txt").write_text(format_timestamps(times))


def write_poses(path: Path, poses: np.ndarray) -> None:
    """KITTI odometry style: one row-major 3x4 sensor -> world pose per line."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(matrix_line(T[:3, :4]) + "\n" for T in poses))


def write_trajectory(path: Path, times: np.ndarray, poses: np.ndarray) -> None:
    """GNSS/INS trajectory: per line the time (s) and the row-major 3x4 sensor -> world pose."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        "".join(f"{t:.6f} {matrix_line(T[:3, :4])}\n" for t, T in zip(times, poses, strict=True))
    )


def write_scan(
    out: Path,
    index: int,
    xyz_sensor: np.ndarray,
    intensity: np.ndarray,
    time: np.ndarray,
    compressed: bool = False,
) -> None:
    """One scan: KITTI float32 .bin, or LAZ (per-point time as gps_time) when
    `compressed` (mm resolution, several times smaller, read by the same readers)."""
    folder = out / "velodyne_points" / "data"
    folder.mkdir(parents=True, exist_ok=True)
    if compressed:
        write_laz(
            folder / f"{frame_name(index)}.laz",
            xyz_sensor,
            intensity=np.round(np.clip(intensity, 0.0, 1.0) * LAZ_INTENSITY_SCALE),
            gps_time=time,
            scale=0.001,
            creation_date=datetime.date(*FIXED_DATE),
        )
        return
    scan = np.empty((len(xyz_sensor), 4), dtype=np.float32)
    scan[:, :3] = xyz_sensor
    scan[:, 3] = intensity
    scan.tofile(folder / f"{frame_name(index)}.bin")


def write_image(out: Path, index: int, rgb: np.ndarray) -> None:
    folder = out / "image_02" / "data"
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(
        str(folder / f"{frame_name(index)}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), PNG_OPTIONS
    )


def write_masks(out: Path, index: int, semantic: np.ndarray, instance: np.ndarray) -> None:
    """Per-pixel class and instance ids as 16-bit PNGs (instance ids stay below 65536)."""
    folder = out / "ground_truth" / "masks"
    folder.mkdir(parents=True, exist_ok=True)
    name = frame_name(index)
    cv2.imwrite(str(folder / f"{name}_semantic.png"), semantic.astype(np.uint16), PNG_OPTIONS)
    cv2.imwrite(str(folder / f"{name}_instance.png"), instance.astype(np.uint16), PNG_OPTIONS)


def write_point_truth(out: Path, index: int, arrays: dict[str, np.ndarray]) -> None:
    folder = out / "ground_truth" / "labels"
    folder.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(folder / f"{frame_name(index)}.npz", **arrays)


def write_sweep_times(out: Path, reference: np.ndarray, start: np.ndarray, end: np.ndarray):
    folder = out / "velodyne_points"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "timestamps.txt").write_text(format_timestamps(reference))
    (folder / "timestamps_start.txt").write_text(format_timestamps(start))
    (folder / "timestamps_end.txt").write_text(format_timestamps(end))
