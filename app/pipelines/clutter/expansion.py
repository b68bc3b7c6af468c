"""3D expansion of camera instances: the object's own point cluster instead of a pixel buffer.

A cluster is taken as a clutter object when at least `min_mask_fraction` of its points that the
camera sees lie on the front layer of a mask instance. An object-sized cluster that the instance
explains (at least `min_seed_share` of all its points are instance points) goes whole: its laser
halo, the parts outside the image and the parts the mask missed. Object-sized means no larger
than what an object of the mask's class can be (`CLASS_EXTENT`, `CLASS_HEIGHT`: a person is
not 3 m wide, a bicycle not 2.5 m tall), so a person under a market stall's awning or a bicycle
against a bike rack does not take the stall or the rack. A person merged with such a structure
gives up its masked points even where they are a small share of the cluster (below
`min_mask_fraction`), those within `PERSON_RADIUS` of the instance's densest spot and no higher
than a person (a mask bleeds onto the stall behind and the awning above). Any other chosen
cluster is an object merged with background (a car against a hedge), or background that a mask
grazes at the image border (a fence running out of the view): only its instance points and the
points within `halo_radius` of them go. Masked points at ground level within `halo_radius` of a
removed point (wheels, feet) go with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from app.pipelines.clutter.clusters import FrameClusters
from app.pipelines.clutter.segmenter import CLUTTER_CLASSES

# The largest object of each camera class (index: the segmenter's clutter code, 0 = none; then
# person, rider, car, truck, bus, train, motorcycle, bicycle), metres: horizontal extent (the
# longer side of its box) and top above the ground. Generous (a person with a pram, a camper
# van, an articulated bus), far below a stall with its awning, a shop front or a bike rack.
CLASS_EXTENT = np.array([np.inf, 1.6, 2.6, 7.0, 20.0, 20.0, 60.0, 2.8, 2.4])
CLASS_HEIGHT = np.array([np.inf, 2.3, 2.5, 3.2, 4.5, 4.5, 4.8, 2.3, 2.2])
PERSON = 1 + CLUTTER_CLASSES.index("person")  # the camera's class code of a person
PERSON_RADIUS = 0.5  # metres: a person's masked points lie this close to their mean


@dataclass
class Expansion:
    removed: np.ndarray  # (N,) bool
    cluster_class: np.ndarray  # (C,) uint8 class of each cluster taken whole, 0 = none
    object_sized: np.ndarray  # (C,) bool


@dataclass
class ClusterSizes:
    """Per cluster: the longer side of its horizontal box and its top above the ground."""

    extent: np.ndarray  # (C,) metres
    top: np.ndarray  # (C,) metres

    def within(self, max_extent: float | np.ndarray, max_height: float | np.ndarray) -> np.ndarray:
        return (self.extent <= max_extent) & (self.top <= max_height)

    def fit_class(self, cluster_class: np.ndarray) -> np.ndarray:
        """(C,) bool: an object of the cluster's camera class (0: any) can be that large."""
        return fits_class(self.extent, self.top, cluster_class)


def fits_class(extent: np.ndarray, top: np.ndarray, klass: np.ndarray) -> np.ndarray:
    """bool per object: an object of camera class `klass` (0: any) can be that large."""
    klass = np.clip(np.asarray(klass, dtype=np.int64), 0, len(CLASS_EXTENT) - 1)
    return (np.asarray(extent) <= CLASS_EXTENT[klass]) & (np.asarray(top) <= CLASS_HEIGHT[klass])


def cluster_sizes(xyz: np.ndarray, clusters: FrameClusters) -> ClusterSizes:
    count = clusters.count
    inside = clusters.label >= 0
    label = clusters.label[inside]
    lo = np.full((count, 2), np.inf)
    hi = np.full((count, 2), -np.inf)
    np.minimum.at(lo, label, xyz[inside, :2])
    np.maximum.at(hi, label, xyz[inside, :2])
    top = np.full(count, -np.inf)
    np.maximum.at(top, label, clusters.above_ground[inside])
    return ClusterSizes(np.max(hi - lo, axis=1), top)


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
    sizes: ClusterSizes | None = None,
) -> Expansion:
    """Grow the instance points of one frame to their clusters (see module docstring); with
    `sizes`, only into clusters an object of the instance's class can be."""
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
    seed_class = majority_class(label, mask_class, count, seed)
    whole = chosen & object_sized & (seeds >= min_seed_share * size)
    fits = None if sizes is None else sizes.fit_class(seed_class)
    if fits is not None:
        whole &= fits
    # only whole objects carry their class on to tracking: a partly covered cluster is background
    cluster_class[whole] = seed_class[whole]
    removed[clustered] = whole[label[clustered]]
    merged = np.zeros(count, dtype=bool)
    if fits is not None:
        # a person merged with what it stands at (a stall, an awning's post) gives up the
        # instance points where the person is, however little or much of the cluster the mask
        # covers; the rest of the mask lies on the structure (bled, or seen past the person)
        merged = (seeds >= max(min_seeds, 1)) & ~fits & (seed_class == PERSON)
        in_merged = clustered & merged[np.where(clustered, label, 0)]
        removed |= _person_core(xyz, clusters.above_ground, instance, in_merged & seed)
    partial = chosen & ~whole & ~merged
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


def _person_core(
    xyz: np.ndarray, above_ground: np.ndarray, instance: np.ndarray, seeds: np.ndarray
) -> np.ndarray:
    """(N,) bool: the `seeds` that can be the person of their instance: within `PERSON_RADIUS`
    of the instance's densest spot and no higher than a person (a mask bled onto the stall
    behind, the awning above or a tree beside lies in the same depth layer). The densest spot,
    not the mean: bled points pull the mean off the person (a tree's 18 points beside a
    person's 24 moved it 0.6 m)."""
    out = np.zeros(len(xyz), dtype=bool)
    at = np.flatnonzero(seeds)
    if not len(at):
        return out
    ids, local = np.unique(instance[at], return_inverse=True)
    xy = xyz[at, :2]
    pairs = cKDTree(xy).query_pairs(PERSON_RADIUS, output_type="ndarray")
    pairs = pairs[local[pairs[:, 0]] == local[pairs[:, 1]]]  # neighbours in the same instance
    both = np.r_[pairs[:, 0], pairs[:, 1]]
    degree = np.bincount(both, minlength=len(at))
    order = np.lexsort((-degree, local))
    first = np.r_[True, local[order][1:] != local[order][:-1]]
    densest = np.zeros(len(at), dtype=bool)
    densest[order[first]] = True  # one point per instance: the most neighbours
    # the centre: the densest point's neighbourhood mean (itself included)
    member = np.r_[np.flatnonzero(densest), pairs[densest[pairs[:, 0]], 1],
                   pairs[densest[pairs[:, 1]], 0]]  # fmt: skip
    count = np.bincount(local[member], minlength=len(ids))
    centre = np.stack([np.bincount(local[member], xy[member, k], len(ids)) for k in range(2)], 1)
    centre /= np.maximum(count, 1)[:, None]
    near = np.linalg.norm(xy - centre[local], axis=1) <= PERSON_RADIUS
    out[at[near & (above_ground[at] <= CLASS_HEIGHT[PERSON])]] = True
    return out


def _within(points: np.ndarray, targets: np.ndarray, radius: float) -> np.ndarray:
    """(len(points),) bool: a target lies within `radius` of the point."""
    distance, _ = cKDTree(targets).query(points, k=1, distance_upper_bound=radius, workers=-1)
    return np.isfinite(distance)
