"""Frames cut into tiles along the trajectory, for pipelines whose unit is the frame (clutter:
labels per frame, rays per frame, tracks from frame to frame).

A frame belongs to the tile of its sensor position's station (`geometry.tiles.TileLayout`). A
tile reads its own frames and, as context, every frame whose sensor was within `halo` metres
(horizontally) of one of its own frames' sensors: the frames whose rays and objects reach its
own. The halo is spatial, not a stretch of stations, so a drive that comes back along a street
sees its first pass there too. Only poses are read: building the tiles costs nothing per point.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from app.geometry.tiles import TileLayout
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
    def build(cls, survey: Survey, length: float, halo: float) -> FrameTiles:
        poses = survey.poses()
        if len(poses) == 0:
            raise ValueError(f"{survey.source}: no frames to cut into tiles")
        sensors = poses[:, :3, 3]
        layout = TileLayout.along(sensors, length, halo)
        owner = layout.owner(layout.stations(sensors))
        tree = cKDTree(sensors[:, :2])
        frames = []
        for tile in range(layout.count):
            own = np.flatnonzero(owner == tile)
            near = tree.query_ball_point(sensors[own, :2], r=halo) if len(own) else []
            reach = np.concatenate([own, *[np.asarray(n, dtype=np.int64) for n in near]])
            frames.append(np.unique(reach.astype(np.int64)))
        return cls(layout, owner.astype(np.int64), frames)

    def own(self, tile: int) -> np.ndarray:
        """Ascending indices of the frames tile `tile` owns."""
        return np.flatnonzero(self.owner == tile)

    def tile_survey(self, survey: Survey, tile: int) -> Survey:
        """The survey with only the frames tile `tile` reads (same order)."""
        return replace(survey, frames=[survey.frames[int(k)] for k in self.frames[tile]])
