"""Neighbourhood based segmentation refinement (the paper's Algorithm 1).

Every pillar that is not ground takes the most frequent non-ground label among the pillars of
its N x N neighbourhood (itself included). Ground pillars keep their label: read literally,
Algorithm 1 would hand every ground pillar next to an object the object's label and grow every
object by two pillars. Ties go to the pillar's own label, then to the lower class id.
"""

from __future__ import annotations

import numpy as np

from app.core.labels import PillarClass

_BIAS = 1 << 30


def _keys(pillars: np.ndarray) -> np.ndarray:
    return (pillars[:, 0] + _BIAS) << 32 | (pillars[:, 1] + _BIAS)


def refine(pillars: np.ndarray, labels: np.ndarray, window: int = 5) -> np.ndarray:
    """Refined labels of the occupied `pillars` (P, 2); unoccupied pillars count as ground."""
    keys = _keys(pillars)
    order = np.argsort(keys)
    sorted_keys = keys[order]
    votes = np.zeros((len(pillars), 4), dtype=np.int32)
    half = window // 2
    for dx in range(-half, half + 1):  # N*N shifted lookups, each vectorised over all pillars
        for dy in range(-half, half + 1):
            neighbour = _keys(pillars + [dx, dy])
            pos = np.minimum(np.searchsorted(sorted_keys, neighbour), len(keys) - 1)
            found = sorted_keys[pos] == neighbour
            label = labels[order[pos[found]]]
            np.add.at(votes, (np.flatnonzero(found), label), 1)
    votes[:, PillarClass.ground] = 0
    own = np.zeros_like(votes)
    own[np.arange(len(labels)), labels] = 1
    best = np.argmax(votes * 2 + own, axis=1)  # ties: own label first, then lower class id
    refined = labels.copy()
    change = (labels != PillarClass.ground) & (votes.max(axis=1) > 0)
    refined[change] = best[change]
    return refined.astype(np.uint8)
