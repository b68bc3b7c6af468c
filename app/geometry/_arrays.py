"""Shape checks shared by the geometry modules, so bad input fails with a clear message."""

from __future__ import annotations

import numpy as np


def as_points(values: np.ndarray, dim: int = 3, name: str = "xyz") -> np.ndarray:
    """Return `values` as a float64 (N, dim) array (no copy when already float64)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {arr.shape}")
    return arr


def as_matrix(values: np.ndarray, shape: tuple[int, int], name: str) -> np.ndarray:
    """Return `values` as a float64 matrix of exactly `shape`."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    return arr
