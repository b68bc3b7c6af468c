"""OXTS GNSS/INS packets of KITTI raw drives -> IMU poses.

Follows the KITTI devkit (`convertOxtsToPose.m`, as in pykitti and kiss-icp): latitude/longitude
are projected with a Mercator projection whose scale `cos(lat0)` is fixed by the first packet, the
orientation is Rz(yaw) Ry(pitch) Rx(roll). The world frame is East-North-Up with its origin at the
first GNSS position (translations are made relative to it, rotations stay absolute so z stays up).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.geometry.transforms import euler_to_matrix, make_transform

EARTH_RADIUS_M = 6378137.0
# the packet's values in order, as the devkit's dataformat.txt lists them
OXTS_FIELDS = (
    "lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu",
    "ax", "ay", "az", "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu",
    "pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode", "velmode", "orimode",
)  # fmt: skip
OXTS_FIELD_COUNT = len(OXTS_FIELDS)


def read_oxts_packet(path: Path) -> np.ndarray:
    """The 30 values of one OXTS text packet."""
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except FileNotFoundError:
        raise InputError(path, "OXTS packet is missing") from None
    except ValueError:
        raise InputError(path, "OXTS packet contains non-numeric values") from None
    if values.size != OXTS_FIELD_COUNT:
        raise InputError(path, f"OXTS packet has {values.size} values, expected {OXTS_FIELD_COUNT}")
    if not np.isfinite(values[:6]).all():
        raise InputError(path, "OXTS packet has NaN or infinite position/orientation")
    return values


def mercator_scale(lat0_deg: float) -> float:
    return float(np.cos(np.deg2rad(lat0_deg)))


def mercator_xy(lat_deg: np.ndarray, lon_deg: np.ndarray, scale: float) -> np.ndarray:
    """(N, 2) Mercator metres of the devkit's `latlonToMercator`."""
    mx = scale * np.deg2rad(lon_deg) * EARTH_RADIUS_M
    my = scale * EARTH_RADIUS_M * np.log(np.tan(np.deg2rad(90.0 + lat_deg) / 2.0))
    return np.stack([mx, my], axis=1)


def imu_poses(packets: np.ndarray) -> np.ndarray:
    """(N, 4, 4) IMU -> world (ENU, origin at the first position) from (N, 30) packets."""
    packets = np.atleast_2d(packets)
    scale = mercator_scale(packets[0, 0])
    t = np.column_stack([mercator_xy(packets[:, 0], packets[:, 1], scale), packets[:, 2]])
    t -= t[0]
    return np.stack(
        [make_transform(euler_to_matrix(*p[3:6]), ti) for p, ti in zip(packets, t, strict=True)]
    )
