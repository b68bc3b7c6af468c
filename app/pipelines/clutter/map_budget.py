"""What each frame adds to DUFOMap's map, estimated before any tile runs: the clutter tiles are cut
by it (`io.frame_tiles`), so that a tile reads as many frames as its worker's memory allows
where a fixed count of frames would cut every tile for the worst street. The same reads give
each frame's points, by which the tiles the budget leaves free are evened (`FRAME_WORK_POINTS`).

Measured with `FreeSpaceMap` at 0.1 m (`python -m bench.dufomap_memory`, bench/RESULTS.md):
- a profile scanner's frames are thin planes of rays that never merge: the map grows with the
  length of their rays, 9.8-17.7 kB per kilometre of rays on simulated town, open and highway
  streets (0.85-1.6 MB per frame there);
- a rotating scanner's frames sweep the same space again from a step further on: 1.8 MB per
  frame over 157 frames of a simulated HDL-64E street (3.2 over its first 50), 0.8 kB per
  kilometre of rays.
A scanner of unknown kind is taken as a profile scanner (the larger estimate for its rays).
The map's memory grows about as resolution^-1.6 (`ClutterConfig.dufomap_resolution`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.sensors import SensorKind, kind_of_scanner
from app.io.survey import Survey
from app.pipelines.clutter.config import ClutterConfig

MB_PER_RAY_KM = 0.02  # a profile scanner's map per kilometre of rays (measured: 0.010-0.018)
ROTATING_FRAME_MB = 3.5  # a rotating scanner's map per frame (measured: 1.8, 3.2 at first)
MEASURED_RESOLUTION = 0.1  # metres: the voxels these were measured at
SAMPLE_EVERY = 5  # a profile survey's rays are measured on every 5th frame, interpolated between
# a frame's work besides its points, in points: a clutter tile's time on this machine fitted as
# 0.030 s per frame read and 2.0 s per million points read (four tiles, two cuts of a simulated
# 0.25 km profile survey, residuals within 0.2 s of 11-12 s)
FRAME_WORK_POINTS = 15_000


@dataclass(frozen=True)
class FrameLoads:
    """What each frame of a survey is expected to cost a clutter tile, before any tile runs."""

    map_mb: np.ndarray  # (F,) megabytes it adds to the tile's free-space map
    # (F,) the work it makes: its points and `FRAME_WORK_POINTS` where frames were read (a
    # profile scanner's returns vary threefold between open road and a built-up street), else
    # 1 each (a rotating scanner's frames hold about the same points each)
    work: np.ndarray


def frame_loads(survey: Survey, config: ClutterConfig, every: int = SAMPLE_EVERY) -> FrameLoads:
    """`FrameLoads` of every frame. A profile scanner's frames are read (every `every`-th, one
    at a time) for their rays' length and their points, interpolated between."""
    count = len(survey.frames)
    scale = (MEASURED_RESOLUTION / config.dufomap_resolution) ** 1.6
    if kind_of_scanner(survey.scanner) is SensorKind.ROTATING:
        return FrameLoads(np.full(count, ROTATING_FRAME_MB * scale), np.ones(count))
    if count == 0:
        return FrameLoads(np.zeros(0), np.zeros(0))
    sampled = np.unique(np.r_[np.arange(0, count, max(every, 1)), count - 1])
    ray_km, points = np.zeros(len(sampled)), np.zeros(len(sampled))
    for i, k in enumerate(sampled.tolist()):
        xyz = survey.frames[k].points().xyz
        ray_km[i], points[i] = _ray_km(xyz), len(xyz)
    frames = np.arange(count)
    return FrameLoads(
        np.interp(frames, sampled, ray_km) * MB_PER_RAY_KM * scale,
        np.interp(frames, sampled, points) + FRAME_WORK_POINTS,
    )


def frame_map_mb(survey: Survey, config: ClutterConfig, every: int = SAMPLE_EVERY) -> np.ndarray:
    """(F,) megabytes each frame is expected to add to a tile's free-space map."""
    return frame_loads(survey, config, every).map_mb


def _ray_km(xyz: np.ndarray) -> float:
    """Kilometres of rays from the sensor to a frame's points (sensor coordinates)."""
    return float(np.linalg.norm(xyz, axis=1).sum()) / 1e3
