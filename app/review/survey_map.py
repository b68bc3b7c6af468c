"""The map a viewer shows, built once per survey and cached on disk.

A survey's frames are accumulated in world coordinates (float64) and re-centred on the survey's
local origin as float32 (viser sends float16 positions unless told otherwise, and float32 of
world coordinates loses centimetres). Alongside the points the map keeps what serving it needs:

- `intensity`: each point's return intensity as the sensor gave it (NaN where the survey has
  none), for the viewer's "colour by intensity";
- `rgb`: each point's colour in its own frame's camera image (KITTI image_2: the point projected
  with the camera's calibration, the pixel it lands on), (0, 0, 0) with `has_rgb` False where
  the frame has no image or the point is outside it, for "colour by camera";
- `cell`: each point's pillar on the store grid (an index into `cells`, the occupied pillars),
  so a label change becomes a colour change by one fancy index;
- points ordered by 50 m tile, so the full-resolution points of a tile are one slice;
- `overview`: a 0.2 m voxel-downsampled subset (capped), shown for the whole map;
- the local ground height (5th-percentile grid of the overview), which the brush intersects the
  click ray with.

Building reads every frame twice, one at a time, a map file a chunk at a time (`build_map`: it
never holds the survey's points), and writes the arrays into one folder per survey under
`<cache_dir>/viewer/`, named after everything that could change them. A later open maps the
per-point arrays from disk instead of loading them: the first scene needs only the overview's
points, a tile in focus only its slice, so opening a survey of tens of millions of points takes
about as long as a small one and the server's memory stays bounded. The map is built by the
`prepare:viewer` job queued when a survey of 5 M points or more is imported
(`jobs/survey_tasks.py`), or else by the first viewer to open the survey; a build that finds
the other's finished map keeps that one.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.geometry.ground import GroundModel, estimate_ground
from app.geometry.pillars import PillarGrid
from app.geometry.projection import pixel_indices, project
from app.geometry.voxels import voxel_downsample
from app.io import open_survey
from app.io.accumulate import accumulate
from app.store.models import Survey
from app.store.pillar_labels import STORE_GRID

CACHE_VERSION = 5  # 3: a folder of arrays, the per-point ones memory-mapped; 4: intensity; 5: rgb
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

    @classmethod
    def of(cls, record: Survey) -> MapSource:
        """The map source of a survey record."""
        return cls(
            survey_id=int(record.id),
            source_path=record.source_path,
            format=record.format,
            origin=(record.origin_x, record.origin_y, record.origin_z),
            point_count=record.point_count,
            frame_count=record.frame_count,
        )

    def cache_name(self, overview_points: int) -> str:
        """File name that changes whenever the points or the overview would."""
        path = Path(self.source_path)
        stamp = path.stat().st_mtime_ns if path.exists() else 0
        key = json.dumps(
            [CACHE_VERSION, self.source_path, self.format, self.origin, self.point_count,
             self.frame_count, stamp, overview_points, TILE_SIZE, OVERVIEW_VOXEL, GROUND_CELL]
        )  # fmt: skip
        digest = hashlib.sha1(key.encode()).hexdigest()[:16]
        return f"survey-{self.survey_id}-{digest}"


@dataclass
class SurveyMap:
    origin: np.ndarray  # (3,) float64 world position of local (0, 0, 0)
    xyz: np.ndarray  # (N, 3) float32 local coordinates, ordered by tile
    intensity: np.ndarray  # (N,) float32 sensor units, NaN where the survey has none
    rgb: np.ndarray  # (N, 3) uint8 camera colour, see has_rgb
    has_rgb: np.ndarray  # (N,) bool: the point was seen by its frame's camera
    cell: np.ndarray  # (N,) int32 index into `cells`
    cells: np.ndarray  # (M,) int64 sorted store-grid ids of the occupied pillars
    tile_ids: np.ndarray  # (T,) int64 sorted TILE_GRID ids of the occupied tiles
    tile_start: np.ndarray  # (T + 1,) int64: tile k holds points tile_start[k]:tile_start[k+1]
    overview: np.ndarray  # (K,) int64 sorted point indices
    ground_origin: np.ndarray  # (2,) local xy of ground cell (0, 0)'s centre
    ground_heights: np.ndarray  # (NX, NY) float32 local z
    low: np.ndarray  # (3,) float32 smallest local coordinates (zeros for an empty map)
    high: np.ndarray  # (3,) float32 largest

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
        return self.low, self.high


def accumulate_local(source: MapSource) -> tuple[np.ndarray, np.ndarray]:
    """(local float32 xyz, world float64 xy) of every frame's points (`app.io.accumulate`)."""
    survey = open_survey(source.source_path, source.format)
    amap = accumulate(survey, origin=np.asarray(source.origin, dtype=np.float64))
    return amap.xyz, amap.world_xy


def _local_frames(source: MapSource, with_rgb: bool = True):
    """Per frame (a map file: per chunk), in order: (local float32 xyz, float32 intensity (NaN:
    none), tile id, store cell id from the exact world xy, (n, 3) uint8 camera colour, (n,)
    seen by the camera)."""
    survey = open_survey(source.source_path, source.format)
    origin = np.asarray(source.origin, dtype=np.float64)
    for frame in survey.frames:
        camera = next((c for c in survey.cameras.values() if c.name in frame.image_paths), None)
        for _, cloud in frame.world_chunks():
            world = cloud.xyz
            xyz = (world - origin).astype(np.float32)
            cells = STORE_GRID.point_cell_ids(world[:, :2])
            if cloud.intensity is None:
                intensity = np.full(len(xyz), np.nan, dtype=np.float32)
            else:
                intensity = np.asarray(cloud.intensity, dtype=np.float32)
            rgb, seen = _camera_colours(frame, camera if with_rgb else None, len(xyz))
            yield xyz, intensity, TILE_GRID.point_cell_ids(xyz[:, :2]), cells, rgb, seen


def _camera_colours(frame, camera, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) uint8 colour of each point of a frame in its camera image and (n,) whether it
    lands there; none seen without a camera or an image. A frame with an image is one chunk:
    its sensor points, in the order of its world points."""
    rgb, seen = np.zeros((n, 3), dtype=np.uint8), np.zeros(n, dtype=bool)
    if camera is None:
        return rgb, seen
    sensor = frame.points().xyz
    if len(sensor) != n:
        return rgb, seen
    proj = project(sensor, camera.P, camera.T_cam_sensor, camera.width, camera.height)
    image = frame.image(camera.name)
    rows, cols = pixel_indices(proj)
    inside = (rows < image.shape[0]) & (cols < image.shape[1])
    seen[np.flatnonzero(proj.in_image)[inside]] = True
    rgb[seen] = image[rows[inside], cols[inside], :3]
    return rgb, seen


class _Union:
    """The sorted union of many id arrays, compacted as it grows (memory: the distinct ids)."""

    def __init__(self, compact_at: int = 8_000_000):
        self.parts: list[np.ndarray] = []
        self.size, self.compact_at = 0, compact_at

    def add(self, ids: np.ndarray) -> None:
        self.parts.append(np.unique(ids))
        self.size += len(self.parts[-1])
        if self.size > self.compact_at:
            self.parts = [self.result()]
            self.size = len(self.parts[0])
            self.compact_at = max(self.compact_at, 2 * self.size)

    def result(self) -> np.ndarray:
        return np.unique(np.concatenate(self.parts)) if self.parts else np.zeros(0, np.int64)


def build_map(source: MapSource, overview_points: int, folder: Path) -> None:
    """The map's arrays into `folder`, streaming: the frames are read twice, one at a time, and
    no array of the survey's points is held in memory. Pass 1 counts the points per tile and
    finds the occupied pillars; pass 2 writes each frame's points into their tiles' slices of
    memory-mapped files. The overview is thinned tile by tile (a 0.2 m voxel never straddles a
    50 m tile), then capped; the ground is estimated from the overview."""
    cells, low, high = _Union(), np.full(3, np.inf), np.full(3, -np.inf)
    tile_counts: dict[int, int] = {}
    for xyz, _, tile, cell, _, _ in _local_frames(source, with_rgb=False):
        ids, counts = np.unique(tile, return_counts=True)
        for t, c in zip(ids.tolist(), counts.tolist(), strict=True):
            tile_counts[t] = tile_counts.get(t, 0) + c
        cells.add(cell)
        if len(xyz):
            low, high = np.minimum(low, xyz.min(axis=0)), np.maximum(high, xyz.max(axis=0))
    tile_ids = np.array(sorted(tile_counts), dtype=np.int64)
    sizes = np.array([tile_counts[t] for t in tile_ids.tolist()], dtype=np.int64)
    tile_start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    n = int(tile_start[-1])
    cell_table = cells.result().astype(np.int64)
    xyz_out = _open_array(folder / "xyz.npy", (n, 3), np.float32)
    cell_out = _open_array(folder / "cell.npy", (n,), np.int32)
    intensity_out = _open_array(folder / "intensity.npy", (n,), np.float32)
    rgb_out = _open_array(folder / "rgb.npy", (n, 3), np.uint8)
    seen_out = _open_array(folder / "has_rgb.npy", (n,), np.bool_)
    filled = tile_start[:-1].copy()
    for xyz, intensity, tile, cell, rgb, seen in _local_frames(source):
        order = np.argsort(tile, kind="stable")
        k = np.searchsorted(tile_ids, tile[order])
        ranks = np.arange(len(order)) - np.searchsorted(k, k)  # position within its tile run
        slots = filled[k] + ranks
        xyz_out[slots] = xyz[order]
        intensity_out[slots] = intensity[order]
        rgb_out[slots] = rgb[order]
        seen_out[slots] = seen[order]
        cell_out[slots] = np.searchsorted(cell_table, cell[order]).astype(np.int32)
        filled += np.bincount(k, minlength=len(tile_ids))
    overview = [
        tile_start[j] + voxel_downsample(np.asarray(xyz_out[tile_start[j] : tile_start[j + 1]]),
                                         OVERVIEW_VOXEL)
        for j in range(len(tile_ids))
    ]  # fmt: skip
    overview = np.concatenate(overview) if overview else np.zeros(0, np.int64)
    if len(overview) > overview_points:
        rng = np.random.default_rng(0)
        overview = np.sort(rng.choice(overview, overview_points, replace=False))
    if n:  # from the overview: one point per 0.2 m voxel keeps every 1 m cell's floor
        ground = estimate_ground(np.asarray(xyz_out[overview], np.float64), cell=GROUND_CELL)
        ground_origin, heights = ground.origin, ground.heights.astype(np.float32)
    else:
        ground_origin, heights = np.zeros(2), np.zeros((1, 1), dtype=np.float32)
        low, high = np.zeros(3), np.zeros(3)
    for array in (xyz_out, cell_out, intensity_out, rgb_out, seen_out):
        if isinstance(array, np.memmap):  # an empty map's arrays are plain
            array.flush()
    del xyz_out, cell_out, intensity_out, rgb_out, seen_out
    np.savez(
        folder / "index.npz",
        origin=np.asarray(source.origin, dtype=np.float64),
        cells=cell_table,
        tile_ids=tile_ids,
        tile_start=tile_start,
        overview=overview.astype(np.int64),
        ground_origin=np.asarray(ground_origin, dtype=np.float64),
        ground_heights=heights,
        low=low.astype(np.float32),
        high=high.astype(np.float32),
    )


def _open_array(path: Path, shape: tuple[int, ...], dtype) -> np.ndarray:
    if not shape[0]:  # an empty file cannot be mapped
        np.save(path, np.zeros(shape, dtype=dtype))
        return np.zeros(shape, dtype=dtype)
    return np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)


def _read_map(folder: Path) -> SurveyMap:
    """The cached map: the per-point arrays memory-mapped (read from disk as tiles are shown,
    so the server's memory does not grow with the survey), the rest loaded."""
    with np.load(folder / "index.npz") as index:
        small = {name: index[name] for name in index.files}
    n = int(small["tile_start"][-1])
    mode = "r" if n else None
    return SurveyMap(
        xyz=np.load(folder / "xyz.npy", mmap_mode=mode),
        intensity=np.load(folder / "intensity.npy", mmap_mode=mode),
        rgb=np.load(folder / "rgb.npy", mmap_mode=mode),
        has_rgb=np.load(folder / "has_rgb.npy", mmap_mode=mode),
        cell=np.load(folder / "cell.npy", mmap_mode=mode),
        **small,
    )


def load_map(source: MapSource, cache_dir: Path, overview_points: int) -> SurveyMap:
    """The survey's map from the cache, built (and cached) when missing."""
    cache = cache_dir / "viewer"
    folder = cache / source.cache_name(overview_points)
    if folder.is_dir():
        try:
            return _read_map(folder)
        except (OSError, KeyError, ValueError):
            shutil.rmtree(folder, ignore_errors=True)  # a broken cache is rebuilt
    cache.mkdir(parents=True, exist_ok=True)
    partial = cache / f"{folder.name}.{os.getpid()}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    try:
        build_map(source, overview_points, partial)
        for old in cache.glob(f"survey-{source.survey_id}-*"):
            if old not in (partial, folder) and not _building(old):
                shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink()
        try:
            os.replace(partial, folder)  # never a half-written cache under the final name
        except OSError:
            if not folder.is_dir():
                raise  # else another process (a job, a viewer) finished the same map first
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return _read_map(folder)


def _building(path: Path) -> bool:
    """A `<name>.<pid>.partial` folder whose process still runs (it is building that map)."""
    parts = path.name.split(".")
    if len(parts) < 3 or parts[-1] != "partial" or not parts[-2].isdigit():
        return False
    try:
        os.kill(int(parts[-2]), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's process: it runs
    return True
