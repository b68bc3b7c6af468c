"""Frames cut into tiles along the trajectory, for pipelines whose unit is the frame (clutter:
labels per frame, rays per frame, tracks from frame to frame).

A frame belongs to the tile of its station, the arc length at which its sensor was there (the
sensor positions are the trajectory: a frame is never projected onto it, which would give a
drive's way back its way out's stations). A tile reads its own frames and, as context, every
frame whose sensor was within `halo` metres (horizontally) of one of its own frames' sensors: the
frames whose rays and objects reach its own. The halo is spatial, not a stretch of stations, so a
drive that comes back along a street sees its first pass there too. A tile may also be cut
shorter so that what it reads stays within a budget: each frame weighs what it costs a tile to
hold (by default 1: frames are counted; the clutter pipeline weighs them by what they add to its
free-space map, `clutter/map_budget.py`). Where one frame's context alone is over the budget (the
drive comes back along a street: both passes are context), a tile may read that context and a
third of the budget more: else each frame there would be a tile of its own, reading its whole
context again. Only poses (and the weights given) are read.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from app.geometry.tiles import EVEN_STRETCH, TileLayout
from app.geometry.trajectory import arc_length
from app.io.survey import Survey


@dataclass
class FrameTiles:
    layout: TileLayout
    owner: np.ndarray  # (F,) int64 tile owning each frame
    frames: list[np.ndarray]  # per tile, ascending indices of the frames it reads (own + halo)

    @property
    def count(self) -> int:
        return self.layout.count

    @classmethod
    def build(
        cls,
        survey: Survey,
        length: float,
        halo: float,
        budget: float | None = None,
        weights: np.ndarray | None = None,
        workers: int | None = None,
        cost: np.ndarray | None = None,
    ) -> FrameTiles:
        """Tiles of `length` metres; with `budget`, a tile also ends before the frames it reads
        (its own and their halo's, a drive's other passes included) would weigh more than
        that, or more than one of its frames' context and a third of `budget` where that
        context alone is over `budget`. `weights`: (F,) what each frame weighs (default 1).
        `workers`: the tiles are evened over them (`TileLayout.along`), and where the budget
        then cuts a count that is no multiple of them, the cut is made again from shorter
        equal tiles (0.5 km on two workers: two tiles of 240 m, one cut by the budget, were
        three, the last running alone). `cost`: (F,) the work each frame makes (its points);
        where the budget cut no tile short, the edges are moved so that the tiles' frames
        (own and context) cost about the same (`TileLayout.balanced`), within the budget."""
        poses = survey.poses()
        if len(poses) == 0:
            raise ValueError(f"{survey.source}: no frames to cut into tiles")
        sensors = poses[:, :3, 3]
        layout = TileLayout.along(sensors, length, halo, workers)
        station = arc_length(np.column_stack([sensors[:, :2], np.zeros(len(sensors))]))
        near = cKDTree(sensors[:, :2]).query_ball_point(sensors[:, :2], r=halo)
        if budget is not None:
            weight = np.ones(len(poses)) if weights is None else np.asarray(weights, np.float64)
            if weight.shape != (len(poses),):
                raise ValueError(f"{len(weight)} frame weights for {len(poses)} frames")
            evened = layout
            layout = _cut_by_budget(layout, station, near, weight, budget)
            if workers and layout.count > 1 and layout.count % workers:
                layout = _evened_cut(layout, workers, station, near, weight, budget)
        tiles = cls._of(layout, station, near)
        if cost is not None and (budget is None or layout.count == evened.count):
            # no tile cut short by the budget: the edges are free to even the tiles' work
            if np.shape(cost) != (len(poses),):
                raise ValueError(f"{np.shape(cost)} frame costs for {len(poses)} frames")
            moved = cls._of(layout.balanced(station, cost, length * EVEN_STRETCH), station, near)
            if budget is None or moved.heaviest(weight) <= max(budget, tiles.heaviest(weight)):
                tiles = moved
        return tiles

    @classmethod
    def _of(cls, layout: TileLayout, station: np.ndarray, near: list) -> FrameTiles:
        owner = layout.owner(station)
        frames = []
        for tile in range(layout.count):
            own = np.flatnonzero(owner == tile)
            reach = np.concatenate([own, *[np.asarray(near[k], dtype=np.int64) for k in own]])
            frames.append(np.unique(reach.astype(np.int64)))
        return cls(layout, owner.astype(np.int64), frames)

    def heaviest(self, weight: np.ndarray) -> float:
        """The most any tile's frames (own and context) weigh."""
        return max(float(weight[f].sum()) for f in self.frames)

    def reads(self) -> np.ndarray:
        """(T,) frames each tile reads: what its work grows with."""
        return np.array([len(f) for f in self.frames], dtype=np.int64)

    def own(self, tile: int) -> np.ndarray:
        """Ascending indices of the frames tile `tile` owns."""
        return np.flatnonzero(self.owner == tile)

    def tile_survey(self, survey: Survey, tile: int) -> Survey:
        """The survey with only the frames tile `tile` reads (same order)."""
        return replace(survey, frames=[survey.frames[int(k)] for k in self.frames[tile]])


def _evened_cut(
    layout: TileLayout,
    workers: int,
    station: np.ndarray,
    near: list,
    weight: np.ndarray,
    budget: float,
    tries: int = 3,
) -> TileLayout:
    """`layout` (cut by the budget into a count that is no multiple of `workers`: the evened
    tiles' budget cut added some) cut again from equal tiles of the next multiples' lengths,
    the first whose budget cut is a multiple of `workers`; else `layout` as it was."""
    count = -(-layout.count // workers) * workers
    for _ in range(tries):
        cut = _cut_by_budget(layout.equal(count), station, near, weight, budget)
        if cut.count % workers == 0:
            return cut
        count += workers
    return layout


def _cut_by_budget(
    layout: TileLayout, station: np.ndarray, near: list, weight: np.ndarray, budget: float
) -> TileLayout:
    """`layout`'s trajectory with a tile ending at `length` metres or before the frame that
    would make the frames it reads weigh more than `budget`, or more than that frame's context
    and a third of `budget` where the context alone is over `budget` (else such a frame would
    be a tile on its own). One step per frame (frames, not points)."""
    edges, start, reads, held = [0.0], 0.0, set(), 0.0
    for k in np.argsort(station, kind="stable").tolist():
        s = max(float(station[k]), 0.0)
        new = set(near[k]) - reads
        grown, weighs = reads | new, held + float(weight[list(new)].sum())
        context = float(weight[near[k]].sum())
        limit = max(budget, context + budget / 3)
        if reads and (s - start >= layout.length or weighs > limit) and s > start:
            edges.append(s)
            start, grown, weighs = s, set(near[k]), context
        reads, held = grown, weighs
    return TileLayout(layout.stations_of, layout.length, layout.halo, tuple(edges))
