"""The map a viewer shows, built once per survey and cached on disk.

A survey's frames are accumulated in world coordinates (float64) and re-centred on the survey's
local origin as float32 (viser sends float16 positions unless told otherwise, and float32 of
world coordinates loses centimetres). Alongside the points the map keeps what serving it needs:

- `cell`: each point's pillar on the store grid (an index into `cells`, the occupied pillars),
  so a label change becomes a colour change by one fancy index;
- points ordered by 50 m tile, so the full-resolution points of a tile are one slice;
- `overview`: a 0.2 m voxel-downsampled subset (capped), shown for the whole map;
- the local ground height (5th-percentile grid of the overview), which the brush intersects the
  click ray with.

Building reads every frame (seconds for millions of points), so the arrays are saved as one .npz
per survey under `<cache_dir>/viewer/`, named after everything that could change them; a second
open only loads arrays.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.geometry.ground import GroundModel, estimate_ground
from app.geometry.pillars import PillarGrid
from app.geometry.voxels import voxel_downsample
from app.io import open_survey
from app.io.accumulate import accumulate
from app.store.pillar_labels import STORE_GRID

CACHE_VERSION = 2
TILE_SIZE = 50.0  # metres: the full-resolution unit
OVERVIEW_VOXEL = 0.2  # metres: one overview point per voxel
GROUND_CELL = 1.0  # metres
TILE_GRID = PillarGrid(0.0, 0.0, TILE_SIZE)  # in local coordinates


@dataclass(frozen=True)
class MapSource:
    """What the map of a survey is built from (the survey record's fields that matter)."""

    survey_id: int
    source_path: str
    format: str
    origin: tuple[float, float, float]
    point_count: int
    frame_count: int

    def cache_name(self, overview_points: int) -> str:
        """File name that changes whenever the points or the overview would."""
        path = Path(self.source_path)
        stamp = path.stat().st_mtime_ns if path.exists() else 0
        key = json.dumps(
            [CACHE_VERSION, self.source_path, self.format, self.origin, self.point_count,
             self.frame_count, stamp, overview_points, TILE_SIZE, OVERVIEW_VOXEL, GROUND_CELL]
        )  # fmt: skip
        digest = hashlib.sha1(key.encode()).hexdigest()[:16]
        return f"survey-{self.survey_id}-{digest}.npz"


@dataclass
class SurveyMap:
    origin: np.ndarray  # (3,) float64 world position of local (0, 0, 0)
    xyz: np.ndarray  # (N, 3) float32 local coordinates, ordered by tile
    cell: np.ndarray  # (N,) int32 index into `cells`
    cells: np.ndarray  # (M,) int64 sorted store-grid ids of the occupied pillars
    tile_ids: np.ndarray  # (T,) int64 sorted TILE_GRID ids of the occupied tiles
    tile_start: np.ndarray  # (T + 1,) int64: tile k holds points tile_start[k]:tile_start[k+1]
    overview: np.ndarray  # (K,) int64 sorted point indices
    ground_origin: np.ndarray  # (2,) local xy of ground cell (0, 0)'s centre
    ground_heights: np.ndarray  # (NX, NY) float32 local z

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def ground(self) -> GroundModel:
        return GroundModel(self.ground_origin, GROUND_CELL, self.ground_heights)

    def tile_id_at(self, xy_local: np.ndarray) -> int:
        return int(TILE_GRID.point_cell_ids(np.asarray(xy_local, dtype=np.float64)[None, :2])[0])

    def tile_points(self, tile_id: int) -> np.ndarray:
        """Indices of the points of one tile (empty when the tile holds none)."""
        k = int(np.searchsorted(self.tile_ids, tile_id))
        if k == len(self.tile_ids) or self.tile_ids[k] != tile_id:
            return np.zeros(0, dtype=np.int64)
        return np.arange(self.tile_start[k], self.tile_start[k + 1], dtype=np.int64)

    def cell_index(self, cell_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(index into `cells`, found) for store cell ids; pillars without points are not found."""
        cell_ids = np.asarray(cell_ids, dtype=np.int64)
        k = np.searchsorted(self.cells, cell_ids)
        k = np.minimum(k, max(len(self.cells) - 1, 0))
        found = (self.cells[k] == cell_ids) if len(self.cells) else np.zeros(len(k), dtype=bool)
        return k, found

    def cell_centres(self, indices: np.ndarray) -> np.ndarray:
        """(n, 2) local xy of the centres of pillars `cells[indices]`."""
        ix, iy = STORE_GRID.decode(self.cells[indices])
        return STORE_GRID.cell_center(ix, iy) - self.origin[:2]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) local corner; zeros for an empty map."""
        if not len(self.xyz):
            return np.zeros(3, dtype=np.float32), np.zeros(3, dtype=np.float32)
        return self.xyz.min(axis=0), self.xyz.max(axis=0)

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


def accumulate_local(source: MapSource) -> tuple[np.ndarray, np.ndarray]:
    """(local float32 xyz, world float64 xy) of every frame's points (`app.io.accumulate`)."""
    survey = open_survey(source.source_path, source.format)
    amap = accumulate(survey, origin=np.asarray(source.origin, dtype=np.float64))
    return amap.xyz, amap.world_xy


def build_map(source: MapSource, overview_points: int) -> SurveyMap:
    xyz, world_xy = accumulate_local(source)
    origin = np.asarray(source.origin, dtype=np.float64)
    tile = TILE_GRID.point_cell_ids(xyz[:, :2])
    order = np.argsort(tile, kind="stable")
    xyz, tile = xyz[order], tile[order]
    pillar = STORE_GRID.point_cell_ids(world_xy[order])  # from float64 world xy: exact cells
    del world_xy
    cells, cell = np.unique(pillar, return_inverse=True)
    tile_ids, tile_first = np.unique(tile, return_index=True)
    tile_start = np.append(tile_first, len(xyz)).astype(np.int64)
    overview = voxel_downsample(xyz, OVERVIEW_VOXEL) if len(xyz) else np.zeros(0, np.int64)
    if len(overview) > overview_points:
        rng = np.random.default_rng(0)
        overview = np.sort(rng.choice(overview, overview_points, replace=False))
    if len(xyz):  # from the overview: one point per 0.2 m voxel keeps every 1 m cell's floor
        ground = estimate_ground(xyz[overview].astype(np.float64), cell=GROUND_CELL)
        ground_origin, heights = ground.origin, ground.heights.astype(np.float32)
    else:
        ground_origin, heights = np.zeros(2), np.zeros((1, 1), dtype=np.float32)
    return SurveyMap(
        origin=origin,
        xyz=xyz,
        cell=cell.reshape(-1).astype(np.int32),
        cells=cells.astype(np.int64),
        tile_ids=tile_ids.astype(np.int64),
        tile_start=tile_start,
        overview=overview.astype(np.int64),
        ground_origin=np.asarray(ground_origin, dtype=np.float64),
        ground_heights=heights,
    )


def load_map(source: MapSource, cache_dir: Path, overview_points: int) -> SurveyMap:
    """The survey's map from the cache, built (and cached) when missing."""
    folder = cache_dir / "viewer"
    path = folder / source.cache_name(overview_points)
    if path.exists():
        try:
            with np.load(path) as data:
                return SurveyMap(**{name: data[name] for name in SurveyMap.__dataclass_fields__})
        except (OSError, KeyError, ValueError):
            path.unlink(missing_ok=True)  # a broken cache file is rebuilt
    survey_map = build_map(source, overview_points)
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob(f"survey-{source.survey_id}-*.npz"):
        old.unlink(missing_ok=True)  # older versions of this survey's map
    partial = path.with_name(f"{path.name}.{os.getpid()}.partial")
    with partial.open("wb") as fh:
        np.savez(fh, **survey_map.arrays())
    os.replace(partial, path)  # never a half-written cache file under the final name
    return survey_map
