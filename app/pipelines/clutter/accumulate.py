"""Accumulation (the paper's last step): the clean frames, posed, become the world map.

World coordinates stay float64. With `voxel_dedup` set, one point per voxel is kept (the first
one in frame order), which drops the near-duplicates of many passes over the same surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.geometry.voxels import voxel_downsample
from app.io.survey import Survey


@dataclass
class WorldMap:
    xyz: np.ndarray  # (M, 3) float64 world coordinates
    intensity: np.ndarray | None  # (M,) float32
    source_frame: np.ndarray  # (M,) uint32 index of the frame
    source_index: np.ndarray  # (M,) uint32 index of the point in its frame


def accumulate(
    survey: Survey, removed: list[np.ndarray], voxel_dedup: float | None = None
) -> tuple[WorldMap, WorldMap]:
    """(kept, removed) points of every frame in world coordinates, each frame read once;
    `voxel_dedup` thins the kept map only."""
    kept_parts, removed_parts = [], []
    for i, (f, gone) in enumerate(zip(survey.frames, removed, strict=True)):
        cloud = f.points()
        if len(cloud) != len(gone):
            raise ValueError(f"frame {f.frame_id}: {len(cloud)} points, {len(gone)} decisions")
        world = cloud.xyz @ f.pose[:3, :3].T + f.pose[:3, 3]
        kept_parts.append(_part(world, cloud.intensity, i, np.flatnonzero(~gone)))
        removed_parts.append(_part(world, cloud.intensity, i, np.flatnonzero(gone)))
    kept, gone_map = _world_map(kept_parts), _world_map(removed_parts)
    if voxel_dedup and len(kept.xyz):
        first = voxel_downsample(kept.xyz, voxel_dedup, origin=kept.xyz.min(axis=0))
        kept = WorldMap(
            kept.xyz[first],
            None if kept.intensity is None else kept.intensity[first],
            kept.source_frame[first],
            kept.source_index[first],
        )
    return kept, gone_map


def _part(world, intensity, frame: int, selected: np.ndarray) -> tuple:
    values = None if intensity is None else np.asarray(intensity, np.float32)[selected]
    frames = np.full(len(selected), frame, dtype=np.uint32)
    return world[selected], values, frames, selected.astype(np.uint32)


def _world_map(parts: list[tuple]) -> WorldMap:
    if not parts:
        return WorldMap(np.zeros((0, 3)), None, np.zeros(0, np.uint32), np.zeros(0, np.uint32))
    xyz, intensity, frame, index = zip(*parts, strict=True)
    with_intensity = all(v is not None for v in intensity)
    return WorldMap(
        xyz=np.concatenate(xyz),
        intensity=np.concatenate(intensity) if with_intensity else None,
        source_frame=np.concatenate(frame),
        source_index=np.concatenate(index),
    )
