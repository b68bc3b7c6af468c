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
    survey: Survey, keep: list[np.ndarray], voxel_dedup: float | None = None
) -> WorldMap:
    """The points with `keep[i]` True of every frame i, in world coordinates."""
    xyz, intensity, frame, index = [], [], [], []
    with_intensity = True
    for i, (f, mask) in enumerate(zip(survey.frames, keep, strict=True)):
        cloud = f.points()
        if len(cloud) != len(mask):
            raise ValueError(f"frame {f.frame_id}: {len(cloud)} points, {len(mask)} decisions")
        selected = np.flatnonzero(mask)
        xyz.append(cloud.xyz[selected] @ f.pose[:3, :3].T + f.pose[:3, 3])
        with_intensity &= cloud.intensity is not None
        if with_intensity:
            intensity.append(np.asarray(cloud.intensity, dtype=np.float32)[selected])
        frame.append(np.full(len(selected), i, dtype=np.uint32))
        index.append(selected.astype(np.uint32))
    world = WorldMap(
        xyz=np.concatenate(xyz) if xyz else np.zeros((0, 3)),
        intensity=np.concatenate(intensity) if with_intensity and intensity else None,
        source_frame=np.concatenate(frame) if frame else np.zeros(0, np.uint32),
        source_index=np.concatenate(index) if index else np.zeros(0, np.uint32),
    )
    if voxel_dedup and len(world.xyz):
        first = voxel_downsample(world.xyz, voxel_dedup, origin=world.xyz.min(axis=0))
        world = WorldMap(
            world.xyz[first],
            None if world.intensity is None else world.intensity[first],
            world.source_frame[first],
            world.source_index[first],
        )
    return world
