"""The road: a centreline with curves and slopes, and lines offset from it.

Everything in a simulated street is placed relative to the centreline: lanes, curbs, sidewalks,
building lines, guardrail lines and the paths of the survey vehicle and the traffic. A station
`s` is arc length along the centreline, a lateral offset is positive to the left of the
direction of travel (increasing s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATION_STEP = 0.5  # metres between centreline samples
MAX_BEND = np.pi / 2  # radians one bend turns at most: a street does not circle back over itself


def bends(start: float, end: float, curvature: float) -> tuple[tuple[float, float, float], ...]:
    """The curves of a stretch that turns at `curvature` from `start` to `end`, as real streets do.

    A stretch that would turn more than MAX_BEND (a long survey at a city street's radius would
    circle over its own road several times) becomes bends of at most MAX_BEND, back to back,
    turning left and right in turn: the road never heads back, so no street is passed twice.
    A stretch that turns less is one curve, unchanged.
    """
    bend = MAX_BEND / abs(curvature)
    if end - start <= bend:
        return ((start, end, curvature),)
    edges = np.append(np.arange(start, end, bend), end)
    return tuple(
        (float(s0), float(s1), curvature * (-1) ** k)
        for k, (s0, s1) in enumerate(zip(edges[:-1], edges[1:], strict=True))
        if s1 > s0
    )


@dataclass(frozen=True)
class RoadProfile:
    """Horizontal and vertical alignment of the road.

    `curves` are (start station, end station, curvature 1/m, positive = turning left);
    `grade` is the constant slope (rise / run) plus a vertical curve of amplitude `hill` metres
    over the road's length, so slopes change along the drive.
    """

    length: float
    curves: tuple[tuple[float, float, float], ...] = ()
    grade: float = 0.0
    hill: float = 0.0


@dataclass
class Centerline:
    """Road centre sampled every STATION_STEP metres: xyz, heading, grade at each station."""

    stations: np.ndarray  # (M,)
    xyz: np.ndarray  # (M, 3), z = road surface height
    heading: np.ndarray  # (M,) radians, direction of travel
    slope: np.ndarray  # (M,) dz/ds

    @classmethod
    def from_profile(cls, profile: RoadProfile, margin: float = 40.0) -> Centerline:
        """Sample the road from -margin to length + margin (the scanner sees beyond both ends)."""
        s = np.arange(-margin, profile.length + margin + STATION_STEP / 2, STATION_STEP)
        curvature = np.zeros_like(s)
        for start, end, k in profile.curves:
            curvature[(s >= start) & (s < end)] = k
        # heading is the integral of curvature, position the integral of the heading
        heading = np.concatenate([[0.0], np.cumsum(curvature[:-1] * STATION_STEP)])
        dx = np.cos(heading) * STATION_STEP
        dy = np.sin(heading) * STATION_STEP
        x = np.concatenate([[0.0], np.cumsum(dx[:-1])])
        y = np.concatenate([[0.0], np.cumsum(dy[:-1])])
        zero = np.searchsorted(s, 0.0)
        x, y = x - x[zero], y - y[zero]
        u = np.clip(s / max(profile.length, 1e-9), -0.5, 1.5)
        z = profile.grade * s + profile.hill * np.sin(np.pi * u) ** 2
        slope = np.gradient(z, s)
        return cls(s, np.column_stack([x, y, z]), heading, slope)

    def at(self, station: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xyz (N,3), heading (N,), slope (N,)) at arbitrary stations (linear interpolation)."""
        station = np.atleast_1d(np.asarray(station, dtype=np.float64))
        xyz = np.stack([np.interp(station, self.stations, self.xyz[:, k]) for k in range(3)], -1)
        heading = np.interp(station, self.stations, self.heading)
        slope = np.interp(station, self.stations, self.slope)
        return xyz, heading, slope

    def offset_points(self, station: np.ndarray, lateral: np.ndarray, dz: float = 0.0):
        """World xyz of points at (station, lateral) with height = road height + dz."""
        xyz, heading, _ = self.at(station)
        lateral = np.broadcast_to(np.asarray(lateral, dtype=np.float64), xyz[:, 0].shape)
        left = np.stack([-np.sin(heading), np.cos(heading)], -1)
        out = xyz.copy()
        out[:, :2] += left * lateral[:, None]
        out[:, 2] += dz
        return out

    def line(self, lateral: float, s0: float, s1: float, step: float = STATION_STEP, dz=0.0):
        """Polyline parallel to the centreline at `lateral` metres, from s0 to s1."""
        n = max(int(np.ceil((s1 - s0) / step)), 1)
        stations = np.linspace(s0, s1, n + 1)
        return self.offset_points(stations, np.full(len(stations), lateral), dz)

    @property
    def start(self) -> float:
        return float(self.stations[0])

    @property
    def end(self) -> float:
        return float(self.stations[-1])
