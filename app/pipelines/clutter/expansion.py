"""3D expansion of camera instances: the object's own point cluster instead of a pixel buffer.

A cluster is taken as a clutter object when at least `min_mask_fraction` of its points that the
camera sees lie on the front layer of a mask instance. An object-sized cluster that the instance
explains (at least `min_seed_share` of all its points are instance points) goes whole: its laser
halo, the parts outside the image and the parts the mask missed. Any other chosen cluster is an
object merged with background (a car against a hedge), or background that a mask grazes at the
image border (a fence running out of the view): only its instance points and the points within
`halo_radius` of them go. Masked points at ground level within `halo_radius` of a removed
point (wheels, feet) go with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from app.pipelines.clutter.clusters import FrameClusters


@dataclass
class Expansion:
    removed: np.ndarray  # (N,) bool
    cluster_class: np.ndarray  # (C,) uint8 class of each cluster taken whole, 0 = none
    object_sized: np.ndarray  # (C,) bool


def cluster_shapes(
    xyz: np.ndarray, clusters: FrameClusters, max_extent: float, max_height: float
) -> np.ndarray:
    """(C,) bool: the cluster fits in a `max_extent` box and stays below `max_height`."""
    count = clusters.count
    inside = clusters.label >= 0
    label = clusters.label[inside]
    lo = np.full((count, 2), np.inf)
    hi = np.full((count, 2), -np.inf)
    np.minimum.at(lo, label, xyz[inside, :2])
    np.maximum.at(hi, label, xyz[inside, :2])
    top = np.full(count, -np.inf)
    np.maximum.at(top, label, clusters.above_ground[inside])
    return (np.max(hi - lo, axis=1) <= max_extent) & (top <= max_height)


def majority_class(
    label: np.ndarray, mask_class: np.ndarray, count: int, where: np.ndarray | None = None
) -> np.ndarray:
    """(count,) uint8 most frequent non-zero mask class of each cluster's points (0 if none)."""
    use = (label >= 0) & (mask_class > 0)
    if where is not None:
        use &= where
    votes = np.zeros((count, int(mask_class.max(initial=0)) + 1), dtype=np.int32)
    np.add.at(votes, (label[use], mask_class[use]), 1)
    return np.where(votes.max(axis=1, initial=0) > 0, votes.argmax(axis=1), 0).astype(np.uint8)


def expand_instances(
    xyz: np.ndarray,
    clusters: FrameClusters,
    instance: np.ndarray,
    mask_class: np.ndarray,
    in_view: np.ndarray,
    min_mask_fraction: float,
    object_sized: np.ndarray,
    halo_radius: float,
    min_seed_share: float = 0.2,
    min_seeds: int = 1,
) -> Expansion:
    """Grow the instance points of one frame to their clusters (see module docstring)."""
    count = clusters.count
    removed = np.zeros(len(xyz), dtype=bool)
    cluster_class = np.zeros(count, dtype=np.uint8)
    seed = instance >= 0
    if count == 0 or not seed.any():
        return Expansion(removed | seed, cluster_class, object_sized)
    label = clusters.label
    clustered = label >= 0
    seen = np.bincount(label[clustered & in_view], minlength=count)
    seeds = np.bincount(label[clustered & seed], minlength=count)
    size = np.bincount(label[clustered], minlength=count)
    chosen = (seeds >= max(min_seeds, 1)) & (seeds >= min_mask_fraction * seen)
    whole = chosen & object_sized & (seeds >= min_seed_share * size)
    # only whole objects carry their class on to tracking: a partly covered cluster is background
    cluster_class[whole] = majority_class(label, mask_class, count, seed)[whole]
    removed[clustered] = whole[label[clustered]]
    partial = chosen & ~whole
    in_partial = clustered & partial[np.where(clustered, label, 0)]
    partial_seeds = in_partial & seed
    removed |= partial_seeds
    if halo_radius > 0 and partial_seeds.any():
        near = _within(xyz[in_partial], xyz[partial_seeds], halo_radius)
        removed[np.flatnonzero(in_partial)[near]] = True
    loose = (mask_class > 0) & ~clustered  # masked points at ground level (wheels, feet)
    if halo_radius > 0 and loose.any() and removed.any():
        near = _within(xyz[loose], xyz[removed], halo_radius)
        removed[np.flatnonzero(loose)[near]] = True
    return Expansion(removed, cluster_class, object_sized)


def _within(points: np.ndarray, targets: np.ndarray, radius: float) -> np.ndarray:
    """(len(points),) bool: a target lies within `radius` of the point."""
    distance, _ = cKDTree(targets).query(points, k=1, distance_upper_bound=radius, workers=-1)
    return np.isfinite(distance)
