"""Triangles of a vertex grid: tubes and swept sections (simulated guardrails, reconstructed
ones) are K rings of S vertices joined ring to ring."""

from __future__ import annotations

import numpy as np


def grid_faces(K: int, S: int, wrap: bool) -> np.ndarray:
    """(2 (K-1) S', 3) triangles joining K consecutive rows of S vertices (row-major vertex
    order); `wrap` closes each row into a ring (S' = S), else S' = S - 1."""
    k = np.arange(K - 1)[:, None]
    s = np.arange(S if wrap else S - 1)[None, :]
    s1 = (s + 1) % S
    a, b, c, d = k * S + s, k * S + s1, (k + 1) * S + s1, (k + 1) * S + s
    return np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], 1).reshape(-1, 3)
