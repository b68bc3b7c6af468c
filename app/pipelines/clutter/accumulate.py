"""Accumulation (the paper's last step): the clean frames, posed, become the world map.

The frames are accumulated once (`app.io.accumulate`) and split into the kept and the removed
points. World coordinates stay float64. With `voxel_dedup` set, one point per voxel is kept (the
first one in frame order), which drops the near-duplicates of many passes over the same surface.
"""

from __future__ import annotations

import numpy as np

from app.geometry.voxels import voxel_downsample
from app.io.accumulate import AccumulatedMap, accumulate
from app.io.survey import Survey


def kept_and_removed(
    survey: Survey, removed: list[np.ndarray], voxel_dedup: float | None = None
) -> tuple[AccumulatedMap, AccumulatedMap]:
    """(kept, removed) points of every frame in world coordinates, with their intensities;
    `voxel_dedup` thins the kept map only."""
    full = accumulate(survey, with_intensity=True)
    for frame_id, n, gone in zip(full.frame_ids, full.frame_sizes, removed, strict=True):
        if n != len(gone):
            raise ValueError(f"frame {frame_id}: {n} points, {len(gone)} decisions")
    gone = np.concatenate(removed).astype(bool) if removed else np.zeros(0, dtype=bool)
    kept, gone_map = full.select(~gone), full.select(gone)
    del full
    if voxel_dedup and len(kept.xyz):
        kept = kept.select(voxel_downsample(kept.xyz, voxel_dedup, origin=kept.xyz.min(axis=0)))
    return kept, gone_map
