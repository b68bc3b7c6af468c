"""Object motion by registration: how far a tracked object's own surface moved between frames.

A centroid is a poor speedometer for a partly seen object: driving past a parked car, the scanner
sees its rear, then its side, then its front, and the centroid of the seen points slides by a
metre while the car stands still. Registering the new frame's points onto the previous frame's
points (world coordinates, translation only) measures where the *overlapping* surface went: near
zero for a parked car, the true displacement for a car creeping at 0.5 m/s in a queue.

The ICP is point-to-plane: a car's flank says nothing about motion along it, its rear says
everything, and point-to-point pairs on the flank would pull a creeping car back to rest. Pairs
are weighted by a Cauchy kernel instead of trimmed, because trimming drops exactly the few pairs
that moved (the rear) as outliers. Directions no surface constrains (a wall sliding along itself)
keep their start value through a small ridge term. Two starts are tried, the static hypothesis
(zero) and the track's predicted displacement; the moved start must fit clearly better to win.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from app.geometry.voxels import voxel_downsample

SHAPE_VOXEL = 0.1  # metres: one point per voxel keeps the surface, not the scan density
MAX_SHAPE_POINTS = 400  # more adds time, not accuracy
NORMAL_NEIGHBOURS = 8  # points per local plane fit
MAX_PAIR_DISTANCE = 0.5  # metres: farther pairs are not the same surface
KERNEL = 0.15  # metres: Cauchy scale; pairs this far off their plane count half
RIDGE = 0.05  # share of the pair count added to each direction's weight (damping)
ITERATIONS = 10
CONVERGED = 5e-3  # metres: well below a slow walker's 0.1 s step
GOOD_FIT = 0.03  # metres: a static start that ends this close needs no second start
BETTER_FIT = 0.7  # a moved start must cut the static start's residual to this share to win


@dataclass
class Registrations:
    """One registration per object pair, as arrays."""

    displacement: np.ndarray  # (L, 3) metres: where each previous surface went
    residual: np.ndarray  # (L,) metres: mean distance of the matched points to their planes
    pairs: np.ndarray  # (L,) matched pairs at the end; < 3: no fit (residual inf)


def object_shape(world: np.ndarray, seed: int = 0) -> np.ndarray:
    """(M, 3) float64: one point per `SHAPE_VOXEL` voxel, at most `MAX_SHAPE_POINTS`."""
    if len(world) == 0:
        return world.reshape(0, 3)
    shape = world[voxel_downsample(world, SHAPE_VOXEL)]
    if len(shape) > MAX_SHAPE_POINTS:
        pick = np.random.default_rng(seed).choice(len(shape), MAX_SHAPE_POINTS, replace=False)
        shape = shape[np.sort(pick)]
    return shape


class _Stacked:
    """Many objects in one point array, each re-centred on its previous centroid and placed
    `SPACING` apart along x, so one k-d tree serves every object and no pair crosses two."""

    SPACING = 1000.0  # metres: far beyond an object plus its motion

    def __init__(self, previous: list[np.ndarray], current: list[np.ndarray]):
        centre = np.stack([p.mean(axis=0) for p in previous])
        place = centre - np.arange(len(previous))[:, None] * [self.SPACING, 0.0, 0.0]
        self.target_owner = np.repeat(np.arange(len(previous)), [len(p) for p in previous])
        self.source_owner = np.repeat(np.arange(len(current)), [len(c) for c in current])
        self.target = np.concatenate(previous) - place[self.target_owner]
        self.source = np.concatenate(current) - place[self.source_owner]
        self.tree = cKDTree(self.target)
        self.normals = self._normals()

    def _normals(self) -> np.ndarray:
        """(M, 3) unit normal per target point: least-variance axis of its neighbours."""
        k = min(NORMAL_NEIGHBOURS, len(self.target))
        _, index = self.tree.query(self.target, k=k, distance_upper_bound=MAX_PAIR_DISTANCE)
        missing = index >= len(self.target)  # fewer neighbours near: repeat the point itself
        index = np.where(missing, np.arange(len(self.target))[:, None], index)
        near = self.target[index]
        local = near - near.mean(axis=1, keepdims=True)
        return np.linalg.eigh(np.einsum("mki,mkj->mij", local, local))[1][:, :, 0]

    def icp(
        self, start: np.ndarray, chosen: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per object (the `chosen` ones; default all), t with source + t on the target
        surface: (t, residual, pairs); objects not chosen keep t = start, no fit."""
        count = len(start)
        t = start.astype(np.float64).copy()
        residual = np.full(count, np.inf)
        pairs = np.zeros(count, dtype=np.int64)
        active = np.ones(count, dtype=bool) if chosen is None else chosen.copy()
        for _ in range(ITERATIONS):
            moving = active[self.source_owner]
            source, owner = self.source[moving], self.source_owner[moving]
            distance, index = self.tree.query(
                source + t[owner], distance_upper_bound=MAX_PAIR_DISTANCE
            )
            matched = np.isfinite(distance)
            owner, index = owner[matched], index[matched]
            n = self.normals[index]
            off = np.einsum("mi,mi->m", source[matched] + t[owner] - self.target[index], n)
            w = 1.0 / (1.0 + (off / KERNEL) ** 2)
            pairs[active] = np.bincount(owner, minlength=count)[active]
            summed = np.bincount(owner, weights=np.abs(off), minlength=count)
            fit = active & (pairs >= 3)
            residual[active] = np.inf
            residual[fit] = summed[fit] / pairs[fit]
            a = np.empty((count, 3, 3))
            for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
                a[:, i, j] = a[:, j, i] = np.bincount(owner, w * n[:, i] * n[:, j], count)
            b = np.stack([np.bincount(owner, -w * off * n[:, i], count) for i in range(3)], 1)
            a[fit] += RIDGE * pairs[fit, None, None] * np.eye(3)
            step = np.zeros((count, 3))
            step[fit] = np.linalg.solve(a[fit], b[fit][:, :, None])[:, :, 0]
            t += step
            active &= (pairs >= 3) & (np.linalg.norm(step, axis=1) >= CONVERGED)
            if not active.any():
                break
        return t, residual, pairs


def register_many(
    previous: list[np.ndarray], current: list[np.ndarray], predicted: np.ndarray
) -> Registrations:
    """How far each `previous[i]` (M, 3) moved to become `current[i]` (K, 3), world coordinates,
    all objects in one batch. `predicted[i]` is the displacement its track expects; the zero
    start is always tried too. Pairs with fewer than 3 points on a side get no fit."""
    count = len(previous)
    out = Registrations(np.zeros((count, 3)), np.full(count, np.inf), np.zeros(count, np.int64))
    usable = [i for i in range(count) if len(previous[i]) >= 3 and len(current[i]) >= 3]
    if not usable:
        return out
    stacked = _Stacked([previous[i] for i in usable], [current[i] for i in usable])
    predicted = np.asarray(predicted, dtype=np.float64).reshape(count, 3)[usable]
    # t moves the current points back onto the previous ones: the displacement is -t
    t, residual, pairs = stacked.icp(np.zeros((len(usable), 3)))
    retry = (residual > GOOD_FIT) & (np.linalg.norm(predicted, axis=1) > MAX_PAIR_DISTANCE / 2)
    if retry.any():
        t2, residual2, pairs2 = stacked.icp(np.where(retry[:, None], -predicted, 0.0), retry)
        better = retry & (residual2 < BETTER_FIT * residual) & (pairs2 >= pairs)
        t[better], residual[better], pairs[better] = t2[better], residual2[better], pairs2[better]
    fitted = pairs >= 3
    out.displacement[usable] = np.where(fitted[:, None], -t, 0.0)
    out.residual[usable] = np.where(fitted, residual, np.inf)
    out.pairs[usable] = pairs
    return out


def register(previous: np.ndarray, current: np.ndarray, predicted: np.ndarray) -> Registrations:
    """`register_many` for one pair (arrays of length 1)."""
    return register_many([previous], [current], np.asarray(predicted).reshape(1, 3))
