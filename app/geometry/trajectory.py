"""The driving trajectory as a polyline: arc length, directions, cross-sections, stations.

The guardrail pipeline cuts roadside points into slices across the driving direction (every
0.5 m in the paper); a point's station (arc length along the drive) says which slice it is in,
and its signed lateral offset says which side of the road it is on (left positive).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from app.geometry._arrays import as_points

_EPS = 1e-9  # metres: consecutive positions closer than this count as the same place


@dataclass
class SlicingPlanes:
    """Planes perpendicular to the driving direction at regular stations."""

    origins: np.ndarray  # (K, 3) float64 points on the trajectory
    normals: np.ndarray  # (K, 3) float64 unit horizontal driving directions (z = 0)
    stations: np.ndarray  # (K,) float64 arc length of each plane


def arc_length(positions: np.ndarray) -> np.ndarray:
    """(M,) cumulative 3D distance along the polyline, starting at 0."""
    positions = as_points(positions, name="positions")
    out = np.zeros(len(positions))
    if len(positions) > 1:
        np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1), out=out[1:])
    return out


def total_length(positions: np.ndarray) -> float:
    """Length of the polyline in metres."""
    s = arc_length(positions)
    return float(s[-1]) if len(s) else 0.0


def _stations(length: float, step: float, include_end: bool) -> np.ndarray:
    """0, step, 2 step, ... <= length (plus `length` itself when asked and not already there)."""
    if not step > 0:
        raise ValueError(f"step must be positive, got {step}")
    stations = np.arange(int(np.floor(length / step + 1e-9)) + 1, dtype=np.float64) * step
    if include_end and length - stations[-1] > 1e-9:
        stations = np.append(stations, length)
    return stations


def _interpolate(s: np.ndarray, values: np.ndarray, stations: np.ndarray) -> np.ndarray:
    """Linear interpolation of the columns of `values` (M, D) at arc lengths `stations`."""
    return np.stack([np.interp(stations, s, values[:, k]) for k in range(values.shape[1])], axis=1)


def resample(positions: np.ndarray, step: float) -> np.ndarray:
    """(K, 3) points every `step` metres of arc length from the first position (linear)."""
    positions = as_points(positions, name="positions")
    if len(positions) == 0:
        raise ValueError("positions is empty: a trajectory needs at least one position")
    s = arc_length(positions)
    return _interpolate(s, positions, _stations(float(s[-1]), step, include_end=False))


def tangents(positions: np.ndarray) -> np.ndarray:
    """(M, 3) unit horizontal driving directions (z = 0) by central differences.

    Repeated positions (a stopped vehicle) are collapsed before differencing and get the
    direction of the place they repeat, so nothing is divided by zero.
    """
    positions = as_points(positions, name="positions")
    xy = positions[:, :2]
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    keep = np.concatenate([[True], step > _EPS])
    unique_xy = xy[keep]
    if len(unique_xy) < 2:
        raise ValueError("trajectory has no horizontal extent: cannot tell the driving direction")
    forward = np.diff(unique_xy, axis=0)  # non-zero by construction
    d = np.empty_like(unique_xy)
    d[0], d[-1] = forward[0], forward[-1]
    d[1:-1] = unique_xy[2:] - unique_xy[:-2]
    # A reversal (p[i+1] == p[i-1]) has no central difference: use the step that arrives there.
    norm = np.linalg.norm(d, axis=1)
    flat = norm <= _EPS
    if np.any(flat):
        idx = np.flatnonzero(flat)
        d[idx] = forward[np.maximum(idx - 1, 0)]
        norm[idx] = np.linalg.norm(d[idx], axis=1)
    unit = d / norm[:, None]
    out = np.zeros_like(positions)
    out[:, :2] = unit[np.cumsum(keep) - 1]
    return out


def _directions_at(positions: np.ndarray, s: np.ndarray, stations: np.ndarray) -> np.ndarray:
    """Unit horizontal directions at arbitrary stations, interpolated from the vertex tangents."""
    t = tangents(positions)
    d = _interpolate(s, t[:, :2], stations)
    norm = np.linalg.norm(d, axis=1)
    flat = norm < 1e-6  # opposite tangents cancel (reversal): take the nearest vertex's
    if np.any(flat):
        nearest = np.clip(np.searchsorted(s, stations[flat]), 0, len(s) - 1)
        d[flat] = t[nearest, :2]
        norm[flat] = 1.0
    out = np.zeros((len(stations), 3))
    out[:, :2] = d / norm[:, None]
    return out


def slicing_planes(positions: np.ndarray, spacing: float) -> SlicingPlanes:
    """Planes across the drive every `spacing` metres of arc length (the paper cuts every 0.5 m)."""
    positions = as_points(positions, name="positions")
    s = arc_length(positions)
    stations = _stations(float(s[-1]) if len(s) else 0.0, spacing, include_end=False)
    origins = _interpolate(s, positions, stations)
    normals = _directions_at(positions, s, stations)
    return SlicingPlanes(origins=origins, normals=normals, stations=stations)


class StationIndex:
    """A finely resampled trajectory with a KD-tree, built once and queried for many frames.

    Only every ~1 m sample goes into the KD-tree: a thin line of 5 cm samples makes queries from
    tens of metres away several times slower. The nearest fine sample is then found by a
    vectorised binary search between the neighbouring coarse samples, on the sign of the
    along-track offset (positive while the sample is still behind the point's foot).
    """

    coarse_step: float = 1.0  # metres between the samples in the KD-tree

    def __init__(self, positions: np.ndarray, step: float = 0.05):
        positions = as_points(positions, name="positions")
        s = arc_length(positions)
        self.length = float(s[-1]) if len(s) else 0.0
        self.stations = _stations(self.length, step, include_end=True)
        self.points = _interpolate(s, positions, self.stations)[:, :2]
        self.directions = _directions_at(positions, s, self.stations)[:, :2]
        self._stride = max(1, round(self.coarse_step / step))
        self._coarse = np.arange(0, len(self.stations), self._stride)
        self._tree = cKDTree(self.points[self._coarse])

    def _offsets(self, xy: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(along, lateral) of each point in the frame of fine sample j."""
        dx = xy[:, 0] - self.points[j, 0]
        dy = xy[:, 1] - self.points[j, 1]
        tx, ty = self.directions[j, 0], self.directions[j, 1]
        return dx * tx + dy * ty, tx * dy - ty * dx

    def query(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(station, lateral) per point; see `station_offsets`."""
        xy = as_points(xyz)[:, :2]
        last = len(self.stations) - 1
        _, c = self._tree.query(xy, k=1, workers=-1)
        centre = self._coarse[c]
        lo = np.maximum(centre - self._stride, 0)
        hi = np.minimum(centre + self._stride, last)
        # Largest j in [lo, hi] whose sample is not past the foot (along >= 0); lo if none.
        while np.any(lo < hi):
            mid = (lo + hi + 1) // 2
            ahead = self._offsets(xy, mid)[0] >= 0.0
            lo = np.where(ahead, mid, lo)
            hi = np.where(ahead, hi, mid - 1)
        # The foot lies between samples lo and lo + 1: refine from the nearer one.
        along, lateral = self._offsets(xy, lo)
        nxt = np.minimum(lo + 1, last)
        along_n, lateral_n = self._offsets(xy, nxt)
        use_next = (nxt != lo) & (np.abs(along_n) < np.abs(along))
        j = np.where(use_next, nxt, lo)
        along = np.where(use_next, along_n, along)
        lateral = np.where(use_next, lateral_n, lateral)
        return self.stations[j] + along, lateral


def station_offsets(
    xyz: np.ndarray, positions: np.ndarray, step: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Station (arc length of the nearest trajectory point, refined along the local tangent) and
    signed horizontal lateral offset (left of the driving direction positive) of each point.

    Points before the start or past the end get stations below 0 or above the total length.
    """
    return StationIndex(positions, step).query(xyz)


def slice_index(xyz: np.ndarray, positions: np.ndarray, spacing: float) -> np.ndarray:
    """(N,) int64 slice each point falls into: floor(station / spacing)."""
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    station, _ = station_offsets(xyz, positions)
    return np.floor(station / spacing).astype(np.int64)
