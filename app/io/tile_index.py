"""Which points each tile owns and which frames it must read: one streaming pass over a survey.

`TileIndex.build` reads every frame once, one at a time (a map file a chunk at a time), and
keeps only small sets per tile: the grid cells holding the tile's own points (a cell belongs to
the tile of its centre's station, and its points with it), and per frame a coarse footprint (the
cells its points touch on a grid `FOOTPRINT_CELLS` times coarser). A tile's window is its own
cells dilated by the halo (`geometry.tiles.halo_cells`); the frames it reads are those whose
footprint meets the window. Nothing here holds a survey's points: memory grows with the area
driven, not with the points. The pass may be cut into parts of frames that a cluster's workers
scan side by side (`map_parts`): alone in the run's process, it was the longest step that kept
the workers waiting (8 s of a 113 s guardrail run on a simulated 2 km survey).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import closing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from app.geometry.tiles import TileLayout, cell_indices, cell_keys, halo_cells
from app.io.map_trajectory import map_trajectory
from app.io.survey import Survey

FOOTPRINT_CELLS = 8  # a frame's footprint is kept on cells this many times the tile cell
# frames per part of the pass at most, when a cluster scans the parts side by side (each part
# opens the survey again: 0.1 s for a 2 km simulated one, a quarter of what 256 frames cost)
PART_FRAMES = 256

# runs `fn(spec, parts, part)` for each part given and yields the results as they finish (the
# tiled runs' `map_tiles`, `pipelines.tiling.TileMap`)
PartMap = Callable[[Callable[..., Any], Any, Any, list[int]], Iterator[Any]]


@dataclass
class TileIndex:
    """The tiles of one survey: per tile its own cells, its window cells and its frames."""

    layout: TileLayout
    cell: float  # metres: the grid the ownership and the halo are kept on
    owned_cells: list[np.ndarray]  # per tile, sorted cell keys holding its points
    window_cells: list[np.ndarray]  # per tile, sorted cell keys within the halo of its own
    frames: list[np.ndarray]  # per tile, ascending indices of the frames it reads
    owned_points: np.ndarray  # (T,) int64 points each tile owns
    frame_sizes: np.ndarray  # (F,) int64 points of each frame
    low: np.ndarray  # (3,) float64 the smallest coordinates of any point (an offset for outputs)
    time0: float | None = None  # a map's first point time: every tile bins its passes from it
    # (3,) float64 the mean of all points: a grid every tile anchors there is the whole survey's
    centre: np.ndarray | None = None

    @property
    def count(self) -> int:
        return self.layout.count

    @classmethod
    def build(
        cls,
        survey: Survey,
        length: float,
        halo: float,
        cell: float = 2.0,
        max_points: int | None = None,
        map_parts: PartMap | None = None,
        workers: int | None = None,
    ) -> TileIndex:
        """Stream the survey's frames once (a map file chunk by chunk). The trajectory is the
        frames' sensor positions, a map's recorded one, or else the one its points trace
        (`map_trajectory`, one more pass). Tiles are `length` metres long, shorter where they
        would own more than `max_points` points (`TileLayout.cut_by_points`): a dense scanner's
        tile fits a worker as a sparse one's does. The windows are then counted as they are on
        the ground, and a tile whose window still holds more (the drive came back along the
        street: both passes are in it) is halved until it fits or is as short as it may be.

        With `map_parts`, the pass is cut into parts of at most `PART_FRAMES` frames scanned there
        (a cluster's workers reopen the survey from its source); without it, this process
        scans the frames as they are."""
        poses = survey.poses()
        if len(poses) == 0:
            raise ValueError(f"{survey.source}: no frames to cut into tiles")
        path, time0 = poses[:, :3, 3], None
        if survey.is_map and survey.trajectory is None:
            path, time0 = map_trajectory(survey)
        layout = TileLayout.along(path, length, halo, workers)
        scan = _scan(survey, cell, map_parts)
        footprints, sizes, low, total = scan.footprints, scan.sizes, scan.low, scan.total
        keys, per_key = scan.keys, scan.counts
        stations = layout.stations(_centres(keys, cell))
        if max_points is not None:
            layout = layout.cut_by_points(stations, per_key, max_points, min_length=2 * cell)
        while True:  # the windows as they are on the ground, cut again where still too full
            tile = layout.owner(stations)  # a cell belongs to the tile of its centre's station
            order = np.argsort(tile, kind="stable")
            starts = np.searchsorted(tile[order], np.arange(layout.count + 1))
            owned_cells = [
                np.sort(keys[order[a:b]]) for a, b in zip(starts[:-1], starts[1:], strict=True)
            ]
            window_cells = [halo_cells(c, halo, cell) for c in owned_cells]
            if max_points is None:
                break
            full = [
                t for t, w in enumerate(window_cells) if _points_in(w, keys, per_key) > max_points
            ]
            split = layout.halved(full, min_length=2 * cell)
            if split.count == layout.count:
                break
            layout = split
        counts = np.bincount(tile, weights=per_key, minlength=layout.count).astype(np.int64)
        frame_of = np.repeat(np.arange(len(footprints)), [len(fp) for fp in footprints])
        footprint = np.concatenate(footprints)
        frames, coarse = [], cell * FOOTPRINT_CELLS
        for window in window_cells:  # the coarse cells holding a window cell's centre
            touched = np.isin(footprint, np.unique(cell_keys(_centres(window, cell), coarse)))
            frames.append(np.unique(frame_of[touched]))
        low = np.where(np.isfinite(low), low, 0.0)
        centre = total / max(int(sizes.sum()), 1)
        return cls(
            layout, cell, owned_cells, window_cells, frames, counts, sizes, low, time0, centre
        )

    def points_read(self) -> np.ndarray:
        """(T,) points each tile reads (its frames' points): what its work grows with."""
        return np.array([int(self.frame_sizes[f].sum()) for f in self.frames], dtype=np.int64)

    def tile_survey(self, survey: Survey, tile: int) -> Survey:
        """The survey with only the frames tile `tile` reads (same order)."""
        return replace(survey, frames=[survey.frames[int(k)] for k in self.frames[tile]])

    def in_window(self, xyz: np.ndarray, tile: int) -> np.ndarray:
        """(N,) bool: the point lies in a cell of the tile's window."""
        return np.isin(cell_keys(xyz, self.cell), self.window_cells[tile])

    def owned(self, xyz: np.ndarray, tile: int) -> np.ndarray:
        """(N,) bool: tile `tile` owns the point (it owns the point's cell)."""
        return np.isin(cell_keys(xyz, self.cell), self.owned_cells[tile])


@dataclass
class FrameScan:
    """What the pass keeps of a run of frames: their sizes and coarse footprints, the smallest
    coordinates and the sum of their points, and the points per grid cell."""

    sizes: np.ndarray  # (F,) int64
    footprints: list[np.ndarray]  # per frame, sorted coarse cell keys its points touch
    low: np.ndarray  # (3,) float64 (inf where there are no points)
    total: np.ndarray  # (3,) float64
    keys: np.ndarray  # sorted cell keys
    counts: np.ndarray  # points in each
    part: int = field(default=0, compare=False)

    @classmethod
    def of(cls, frames: list, cell: float, part: int = 0) -> FrameScan:
        """Stream `frames` one at a time (a map file chunk by chunk)."""
        coarse = cell * FOOTPRINT_CELLS
        cells = _CellCounts()
        footprints, sizes = [], []
        low, total = np.full(3, np.inf), np.zeros(3)
        for frame in frames:
            size, footprint = 0, []
            for _, cloud in frame.world_chunks():
                xyz = cloud.xyz
                size += len(xyz)
                if len(xyz):
                    low = np.minimum(low, xyz.min(axis=0))
                    total += xyz.sum(axis=0)
                keys, per_key = np.unique(cell_keys(xyz, cell), return_counts=True)
                cells.add(keys, per_key)
                footprint.append(np.unique(cell_keys(_centres(keys, cell), coarse)))
            sizes.append(size)
            footprints.append(np.unique(np.concatenate(footprint)))
        keys, counts = cells.totals()
        sizes = np.asarray(sizes, dtype=np.int64)
        return cls(sizes, footprints, low, total, keys, counts, part)

    @classmethod
    def joined(cls, parts: list[FrameScan]) -> FrameScan:
        """The scan of the parts' frames one after the other (`parts` in frame order)."""
        cells = _CellCounts()
        for p in parts:
            cells.add(p.keys, p.counts)
        keys, counts = cells.totals()
        return cls(
            np.concatenate([p.sizes for p in parts]),
            [f for p in parts for f in p.footprints],
            np.min([p.low for p in parts], axis=0),
            np.sum([p.total for p in parts], axis=0),
            keys,
            counts,
        )


@dataclass(frozen=True)
class ScanSpec:
    """What a worker needs to scan a part of a survey's frames: names, not objects."""

    survey_source: str
    survey_format: str
    cell: float


def scan_part(spec: ScanSpec, parts: list[tuple[int, int]], part: int) -> FrameScan:
    """Part `part` of the pass as a worker runs it: the survey reopened, frames [a, b)."""
    from app.io.registry import open_survey

    a, b = parts[part]
    frames = open_survey(Path(spec.survey_source), spec.survey_format).frames[a:b]
    return FrameScan.of(frames, spec.cell, part)


def _scan(survey: Survey, cell: float, map_parts: PartMap | None) -> FrameScan:
    """The pass over every frame: here, or in parts through `map_parts`."""
    count = len(survey.frames)
    if map_parts is None or count <= PART_FRAMES:
        return FrameScan.of(survey.frames, cell)
    bounds = np.linspace(0, count, -(-count // PART_FRAMES) + 1).astype(int).tolist()
    parts = list(zip(bounds[:-1], bounds[1:], strict=True))  # of equal size, in frame order
    spec = ScanSpec(str(Path(survey.source).resolve()), survey.format, cell)
    with closing(map_parts(scan_part, spec, parts, list(range(len(parts))))) as finished:
        scans = sorted(finished, key=lambda s: s.part)
    return FrameScan.joined(scans)


def _points_in(window: np.ndarray, keys: np.ndarray, per_key: np.ndarray) -> int:
    """Points in the cells `window` (`keys` sorted, `per_key` their points)."""
    if len(keys) == 0:
        return 0
    at = np.minimum(np.searchsorted(keys, window), len(keys) - 1)
    return int(per_key[at][keys[at] == window].sum())


def _centres(keys: np.ndarray, cell: float) -> np.ndarray:
    i, j = cell_indices(keys)
    return np.column_stack([(i + 0.5) * cell, (j + 0.5) * cell])


class _CellCounts:
    """Points per grid cell over a stream of frames: merged every few frames, so memory grows
    with the cells of the area driven, not with the frames that touched them."""

    def __init__(self, merge_every: int = 64):
        self.keys = np.zeros(0, dtype=np.int64)
        self.counts = np.zeros(0, dtype=np.int64)
        self.pending: list[tuple[np.ndarray, np.ndarray]] = []
        self.merge_every = merge_every

    def add(self, keys: np.ndarray, counts: np.ndarray) -> None:
        self.pending.append((keys, counts))
        if len(self.pending) >= self.merge_every:
            self._merge()

    def _merge(self) -> None:
        keys = np.concatenate([self.keys, *[k for k, _ in self.pending]])
        counts = np.concatenate([self.counts, *[c for _, c in self.pending]])
        self.pending = []
        self.keys, inverse = np.unique(keys, return_inverse=True)
        self.counts = np.bincount(inverse, weights=counts, minlength=len(self.keys)).astype(
            np.int64
        )

    def totals(self) -> tuple[np.ndarray, np.ndarray]:
        """(sorted cell keys, points in each)."""
        self._merge()
        return self.keys, self.counts
