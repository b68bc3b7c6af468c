"""Validation splits that keep space whole: labels are held out by blocks of the map (or of
the road), never one by one, because neighbouring pillars or slices share most of what a
model sees and would otherwise validate on near-copies of training samples."""

from __future__ import annotations

import numpy as np


def held_out_blocks(
    positions: np.ndarray,
    block_size: float,
    fraction: float,
    seed: int,
    classes: np.ndarray | None = None,
) -> np.ndarray:
    """(L,) True for the samples in the blocks held out for validation.

    `positions` (L, D) metres (a pillar centre, a station along the road); blocks are
    `block_size` cubes of that space. About `fraction` of the blocks are drawn at random but
    reproducibly (`seed`): at least one, and never all when there are two or more.

    With `classes` (L,), every class found in two or more blocks gets blocks on both sides,
    rarest class first (one block more or less each): labels cluster where a person worked, and
    a validation without the rare class cannot see a model that lost it.
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
    if classes is not None and len(keys) >= 2:
        cover_classes(chosen, inverse, np.asarray(classes), rng)
    return chosen[inverse]


def cover_classes(
    chosen: np.ndarray, inverse: np.ndarray, classes: np.ndarray, rng: np.random.Generator
) -> None:
    """Move blocks so that each class in two or more blocks lies on both sides (in place)."""
    found, counts = np.unique(classes, return_counts=True)
    for c in found[np.argsort(counts, kind="stable")]:
        blocks = np.unique(inverse[classes == c])
        if len(blocks) < 2:
            continue
        if not chosen[blocks].any():
            chosen[rng.choice(blocks)] = True
        elif chosen[blocks].all():
            chosen[rng.choice(blocks)] = False
    if chosen.all():  # never every block
        chosen[rng.integers(len(chosen))] = False
