"""Validation splits that keep space whole: labels are held out by blocks of the map (or of
the road), never one by one, because neighbouring pillars or slices share most of what a
model sees and would otherwise validate on near-copies of training samples."""

from __future__ import annotations

import numpy as np


def held_out_blocks(
    positions: np.ndarray, block_size: float, fraction: float, seed: int
) -> np.ndarray:
    """(L,) True for the samples in the blocks held out for validation.

    `positions` (L, D) metres (a pillar centre, a station along the road); blocks are
    `block_size` cubes of that space. About `fraction` of the blocks are drawn at random but
    reproducibly (`seed`): at least one, and never all when there are two or more.
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(len(positions), -1)
    block = np.floor(positions / block_size).astype(np.int64)
    keys, inverse = np.unique(block, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    rng = np.random.default_rng(seed)
    count = int(round(fraction * len(keys)))
    count = min(max(count, 1), max(len(keys) - 1, 1))
    chosen = np.zeros(len(keys), dtype=bool)
    chosen[rng.choice(len(keys), size=count, replace=False)] = True
    return chosen[inverse]
