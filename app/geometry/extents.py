"""Per-label extents: the lower and upper corner of each label's values (a cluster's or an
instance's points in 3D, or its pixels on an image), with ufunc.at over the labels, no sort."""

from __future__ import annotations

import numpy as np


def label_extents(
    values: np.ndarray, label: np.ndarray, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """((count, d) low, (count, d) high) of `values` (n, d) per `label` (n,) in 0..count-1;
    +inf / -inf for a label without values."""
    values = np.asarray(values, dtype=np.float64)
    low = np.full((count, values.shape[1]), np.inf)
    high = np.full((count, values.shape[1]), -np.inf)
    np.minimum.at(low, label, values)
    np.maximum.at(high, label, values)
    return low, high
