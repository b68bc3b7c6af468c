"""Frames cut into tiles along the trajectory, for pipelines whose unit is the frame (clutter:
labels per frame, rays per frame, tracks from frame to frame).

A frame belongs to the tile of its station, the arc length at which its sensor was there (the
sensor positions are the trajectory: a frame is never projected onto it, which would give a
drive's way back its way out's stations). A tile reads its own frames and, as context, every
frame whose sensor was within `halo` metres (horizontally) of one of its own frames' sensors: the
frames whose rays and objects reach its own. The halo is spatial, not a stretch of stations, so a
drive that comes back along a street sees its first pass there too. A tile may also be cut
shorter so that it reads at most a number of frames where the frames are dense. Where one
frame's context alone is over that number (the drive comes back along a street: both passes are
context), a tile may read that context and a third of the number more: else each frame there
would be a tile of its own, reading its whole context again. Only poses are read: building the
tiles costs nothing per point.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from app.geometry.tiles import TileLayout
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
        cls, survey: Survey, length: float, halo: float, max_reads: int | None = None
    ) -> FrameTiles:
        """Tiles of `length` metres; with `max_reads`, a tile also ends before it would read
        more than that many frames (its own and their halo's, a drive's other passes
        included), or one of its frames' context and a third of `max_reads` more where that
        context alone is over `max_reads`."""
        poses = survey.poses()
        if len(poses) == 0:
            raise ValueError(f"{survey.source}: no frames to cut into tiles")
        sensors = poses[:, :3, 3]
        layout = TileLayout.along(sensors, length, halo)
        station = arc_length(np.column_stack([sensors[:, :2], np.zeros(len(sensors))]))
        near = cKDTree(sensors[:, :2]).query_ball_point(sensors[:, :2], r=halo)
        if max_reads is not None:
            layout = _cut_by_reads(layout, station, near, max_reads)
        owner = layout.owner(station)
        frames = []
        for tile in range(layout.count):
            own = np.flatnonzero(owner == tile)
            reach = np.concatenate([own, *[np.asarray(near[k], dtype=np.int64) for k in own]])
            frames.append(np.unique(reach.astype(np.int64)))
        return cls(layout, owner.astype(np.int64), frames)

    def reads(self) -> np.ndarray:
        """(T,) frames each tile reads: what its work grows with."""
        return np.array([len(f) for f in self.frames], dtype=np.int64)

    def own(self, tile: int) -> np.ndarray:
        """Ascending indices of the frames tile `tile` owns."""
        return np.flatnonzero(self.owner == tile)

    def tile_survey(self, survey: Survey, tile: int) -> Survey:
        """The survey with only the frames tile `tile` reads (same order)."""
        return replace(survey, frames=[survey.frames[int(k)] for k in self.frames[tile]])


def _cut_by_reads(
    layout: TileLayout, station: np.ndarray, near: list, max_reads: int
) -> TileLayout:
    """`layout`'s trajectory with a tile ending at `length` metres or before the frame that
    would make it read more than `max_reads` frames, or more than that frame's context and a
    third of `max_reads` where the context alone is over `max_reads` (else such a frame would
    be a tile on its own). One step per frame (frames, not points)."""
    edges, start, reads = [0.0], 0.0, set()
    for k in np.argsort(station, kind="stable").tolist():
        s = max(float(station[k]), 0.0)
        grown = reads.union(near[k])
        limit = max(max_reads, len(near[k]) + max_reads // 3)
        if reads and (s - start >= layout.length or len(grown) > limit) and s > start:
            edges.append(s)
            start, grown = s, set(near[k])
        reads = grown
    return TileLayout(layout.stations_of, layout.length, layout.halo, tuple(edges))
