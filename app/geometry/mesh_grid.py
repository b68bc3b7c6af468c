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


def cap_faces(K: int, S: int) -> np.ndarray:
    """(2 S, 3) fan triangles closing both ends of a tube of K rings of S vertices, with the
    start centre at vertex K * S and the end centre at K * S + 1 (appended after the rings)."""
    s = np.arange(S)
    s1 = (s + 1) % S
    last = (K - 1) * S
    start = np.stack([np.full(S, K * S), s1, s], -1)
    end = np.stack([np.full(S, K * S + 1), last + s, last + s1], -1)
    return np.concatenate([start, end])
