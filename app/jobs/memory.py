"""Refusing a job that cannot fit in memory when it is queued, not when a worker runs out.

Each job kind may register an estimate (`@task(kind, estimate=fn)`, fn(session, survey_id,
config) -> MemoryEstimate): the memory its run needs, as a sum of terms, each tied to the
config field (or the survey) it grows with. A job whose estimate exceeds
`MMSCLEAN_JOB_MEMORY_MB` is a ConfigError naming the term's field that needs the most, with the
estimate in the message, so a user sees what to change.

The estimates are models fitted to measurements, deliberately on the generous side:

- DUFOMap's octree (the free-space map) grows with the rays it carves: about 9 bytes per
  point and metre of ray at 0.1 m voxels, times (0.1 m / r)^1.6 at other resolutions r
  (measured: 1,234,476 points of SemanticKITTI 04, mean ray 17 m: 58 / 182 / 559 MB at
  0.2 / 0.1 / 0.05 m; 1,381,077 points of the urban sample, mean ray 7 m: 20 / 89 / 268 MB).
  The store keeps no ray lengths, so every ray counts as `MEAN_RAY_M`.
- A per-frame grid over the frame's footprint (the ground model) is a dense array: cells of
  (2 x sensor reach / cell)^2 at about 40 bytes each.
- Point arrays: a fixed number of bytes per point of the survey for each pipeline.
- The worker itself (Python, numpy, torch, a network): `WORKER_BASE_MB`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.core.errors import ConfigError
from app.geometry.tiles import EVEN_STRETCH
from app.store.surveys import SurveyFootprint

MB = 1024**2
WORKER_BASE_MB = 500.0  # a worker after importing the pipelines (measured ~380 MB) plus a network
SENSOR_REACH_M = 100.0  # farthest points of a rotating scanner: a frame spans 2 x this
MEAN_RAY_M = 20.0  # mean sensor-to-point distance (SemanticKITTI 04: 17 m)
DUFOMAP_BYTES_PER_POINT_METRE = 9.0  # at 0.1 m voxels (see the module docstring)
DUFOMAP_EXPONENT = 1.6
GRID_CELL_BYTES = 40.0  # a dense float64 grid, its nearest-fill indices and opening
LIMIT_SETTING = "MMSCLEAN_JOB_MEMORY_MB"


@dataclass(frozen=True)
class Need:
    field: str  # what the user changes to need less: "config.dufomap_resolution", "survey_id"
    mb: float
    what: str  # e.g. "0.001 m free-space voxels"


@dataclass
class MemoryEstimate:
    survey: str  # what the estimate knew of the survey, e.g. "survey 1,234,476 points"
    needs: list[Need] = field(default_factory=list)

    @property
    def total_mb(self) -> float:
        return WORKER_BASE_MB + sum(n.mb for n in self.needs)

    def add(self, field_name: str, mb: float, what: str) -> MemoryEstimate:
        self.needs.append(Need(field_name, mb, what))
        return self


def survey_text(footprint: SurveyFootprint) -> str:
    """'survey 1,234,476 points, 10 frames, trajectory 12 x 0 x 0 m'."""
    low, high = footprint.trajectory_min, footprint.trajectory_max
    span = [hi - lo for lo, hi in zip(low, high, strict=True)]
    return (
        f"survey {footprint.points:,} points, {footprint.frames:,} frames, trajectory "
        + " x ".join(f"{s:,.0f}" for s in span)
        + " m"
    )


def extent_text(footprint: SurveyFootprint) -> str:
    """The area the estimate assumes: the trajectory widened by the sensor's reach."""
    x, y = (
        hi - lo + 2 * SENSOR_REACH_M
        for lo, hi in zip(footprint.trajectory_min[:2], footprint.trajectory_max[:2], strict=True)
    )
    return f"{x:,.0f} x {y:,.0f} m"


def tile_reach(tile_length: float, halo: float) -> float:
    """Metres of trajectory a tile reads at most: its length, stretched as far as evening the
    tiles over the workers may (`TileLayout.along`), and its halo on both sides."""
    return EVEN_STRETCH * tile_length + 2 * halo


def tile_share(footprint: SurveyFootprint, metres: float) -> float:
    """The share of the survey's points a tiled run reads for `metres` of trajectory (a tile
    and its halo): the length is taken as the trajectory's bounding-box diagonal, shorter than
    a winding drive, so the share comes out generous."""
    low, high = np.asarray(footprint.trajectory_min), np.asarray(footprint.trajectory_max)
    return min(1.0, metres / max(float(np.linalg.norm(high - low)), 1.0))


def bounded_tile_points(
    footprint: SurveyFootprint, reach: float, halo: float, cell: float, max_points: int
) -> float:
    """Points a tile of `reach` metres reads, where the tile index cuts a tile shorter once its
    window would hold more than `max_points` (`io.tile_index`), down to the shortest tile (two
    `cell`s), whose window is still its halo."""
    shortest = tile_share(footprint, 2 * cell + 2 * halo)
    share = tile_share(footprint, reach)
    return min(footprint.points * share, max(max_points, footprint.points * shortest))


def tile_field(footprint: SurveyFootprint, tile_length: float) -> str:
    """The config field a tile's memory answers to: shorter tiles need less while the survey
    spans several; a survey within one tile cannot."""
    return "config.tile_length" if tile_share(footprint, tile_length) < 1.0 else "survey_id"


def points_mb(footprint: SurveyFootprint, bytes_per_point: float) -> float:
    return footprint.points * bytes_per_point / MB


def dufomap_mb(footprint: SurveyFootprint, resolution: float) -> float:
    """DUFOMap's octree for the whole survey at `resolution` metres (module docstring)."""
    scale = (0.1 / resolution) ** DUFOMAP_EXPONENT
    return footprint.points * MEAN_RAY_M * DUFOMAP_BYTES_PER_POINT_METRE * scale / MB


def frame_grid_mb(cell: float) -> float:
    """A dense grid of `cell`-metre cells over one frame's footprint."""
    side = 2 * SENSOR_REACH_M / cell
    return side * side * GRID_CELL_BYTES / MB


def check_memory(estimate: MemoryEstimate, limit_mb: int) -> None:
    """ConfigError naming the largest term's field when the estimate exceeds the limit."""
    total = estimate.total_mb
    if total <= limit_mb:
        return
    largest = max(estimate.needs, key=lambda n: n.mb, default=Need("survey_id", 0.0, ""))
    what = f"; {largest.what}" if largest.what else ""
    raise ConfigError(
        largest.field,
        f"this run needs about {total:,.0f} MB ({estimate.survey}{what}); "
        f"the limit is {limit_mb:,} MB ({LIMIT_SETTING})",
    )
