"""Geometric slice features (beyond the paper, which classifies the camera crop only).

A guardrail slice is low (top about 0.7-1.0 m above the ground), long and straight along the
road, thin across it and at a steady lateral offset; a tree trunk or pole is tall and vertical,
a car is wide and bulky. These per-slice numbers let a classifier (or a check on the CNN) use
that, and they cost one pass of grouped numpy reductions:

- height above the local ground (`app.geometry.ground.estimate_ground`, or the given heights):
  min, 10th / 50th / 90th percentile, max;
- extent along the trajectory, across it (lateral) and vertically; signed and absolute lateral
  offset of the slice;
- density: points, log points, points per metre of trajectory, per m^2 of the along x vertical
  rectangle;
- shape over the slice *and its neighbours* (same component, stations within
  +-`context_slices`): PCA eigenvalues l1 >= l2 >= l3 of the points give linearity
  (l1 - l2) / l1, planarity (l2 - l3) / l1, scattering l3 / l1; the main axis' alignment with
  the driving direction |e1 . t| and with the vertical |e1_z|, and the normal's |e3_z|.
"""

from __future__ import annotations

import numpy as np

from app.geometry.ground import estimate_ground
from app.pipelines.guardrail.slices import SliceSet

FEATURE_NAMES: list[str] = [
    "count",
    "log_count",
    "height_min",
    "height_p10",
    "height_p50",
    "height_p90",
    "height_max",
    "extent_along",
    "extent_lateral",
    "extent_vertical",
    "lateral",
    "abs_lateral",
    "density_per_m",
    "density_per_m2",
    "linearity",
    "planarity",
    "scattering",
    "along_alignment",
    "verticality",
    "normal_z",
    "context_count",
]
CONTEXT_SLICES = 2  # neighbouring slices each way the shape features look at


def _grouped_quantiles(values: np.ndarray, offsets: np.ndarray, qs: list[float]) -> np.ndarray:
    """(K, len(qs)) quantiles (lower-rank pick) of each group values[offsets[k]:offsets[k+1]]."""
    counts = np.diff(offsets)
    group = np.repeat(np.arange(len(counts)), counts)
    v = values[np.lexsort((values, group))]
    return np.stack(
        [v[offsets[:-1] + np.floor(q * (counts - 1)).astype(np.int64)] for q in qs], axis=1
    )


def _reduce(ufunc: np.ufunc, values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    return ufunc.reduceat(values, offsets[:-1]) if len(offsets) > 1 else np.zeros(0)


def slice_features(
    xyz_world: np.ndarray,
    slice_set: SliceSet,
    *,
    above_ground: np.ndarray | None = None,
    ground_cell: float = 1.0,
    context_slices: int = CONTEXT_SLICES,
) -> tuple[np.ndarray, list[str]]:
    """(K, D) float32 features of the slices and their column names (`FEATURE_NAMES`).

    `xyz_world`: the points `slice_set` indexes, ideally with the ground still in (the ground
    height comes from them) unless `above_ground` (N,) per-point heights are given, e.g.
    `RoadRemoval.above_ground`. `context_slices`: neighbours each way for the shape features.
    """
    xyz = np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3)
    k = len(slice_set)
    out = np.zeros((k, len(FEATURE_NAMES)), dtype=np.float32)
    if k == 0:
        return out, list(FEATURE_NAMES)
    idx = slice_set.indices
    offsets = slice_set.offsets
    counts = np.diff(offsets).astype(np.float64)
    origin = xyz[idx].mean(axis=0)
    local = xyz[idx] - origin
    if above_ground is None:
        ground = estimate_ground(xyz - origin, cell=ground_cell)
        height = local[:, 2] - ground.height(local)
    else:
        height = np.asarray(above_ground, dtype=np.float64)[idx]
    hq = _grouped_quantiles(height, offsets, [0.0, 0.1, 0.5, 0.9, 1.0])
    st = slice_set.point_station[idx]
    lat = slice_set.point_lateral[idx]
    along = _reduce(np.maximum, st, offsets) - _reduce(np.minimum, st, offsets)
    across = _reduce(np.maximum, lat, offsets) - _reduce(np.minimum, lat, offsets)
    vertical = _reduce(np.maximum, local[:, 2], offsets) - _reduce(np.minimum, local[:, 2], offsets)

    # shape: moments per slice, summed over the neighbouring slices of the same component
    group = np.repeat(np.arange(k), np.diff(offsets))
    s1 = np.stack([np.bincount(group, local[:, a], minlength=k) for a in range(3)], axis=1)
    s2 = np.stack(
        [
            np.bincount(group, local[:, a] * local[:, b], minlength=k)
            for a in range(3)
            for b in range(3)
        ],
        axis=1,
    ).reshape(k, 3, 3)
    n_ctx, s1_ctx, s2_ctx = counts.copy(), s1.copy(), s2.copy()
    span = (
        int(slice_set.station_index.max() - slice_set.station_index.min()) + 2 * context_slices + 3
    )
    key = slice_set.component.astype(np.int64) * span + slice_set.station_index
    order = np.argsort(key, kind="stable")
    skey = key[order]
    for d in range(-context_slices, context_slices + 1):
        if d == 0:
            continue
        at = np.clip(np.searchsorted(skey, key + d), 0, k - 1)
        hit = skey[at] == key + d
        j = order[at[hit]]
        n_ctx[hit] += counts[j]
        s1_ctx[hit] += s1[j]
        s2_ctx[hit] += s2[j]
    mean = s1_ctx / n_ctx[:, None]
    cov = s2_ctx / n_ctx[:, None, None] - mean[:, :, None] * mean[:, None, :]
    val, vec = np.linalg.eigh(cov)  # ascending
    val = np.clip(val, 0.0, None)
    l1, l2, l3 = val[:, 2], val[:, 1], val[:, 0]
    safe = np.where(l1 > 0, l1, 1.0)
    e1, e3 = vec[:, :, 2], vec[:, :, 0]
    t = slice_set.direction
    alignment = np.abs(e1[:, 0] * t[:, 0] + e1[:, 1] * t[:, 1])

    columns = {
        "count": counts,
        "log_count": np.log1p(counts),
        "height_min": hq[:, 0],
        "height_p10": hq[:, 1],
        "height_p50": hq[:, 2],
        "height_p90": hq[:, 3],
        "height_max": hq[:, 4],
        "extent_along": along,
        "extent_lateral": across,
        "extent_vertical": vertical,
        "lateral": slice_set.lateral,
        "abs_lateral": np.abs(slice_set.lateral),
        "density_per_m": counts / slice_set.spacing,
        "density_per_m2": counts / (np.maximum(along, 0.05) * np.maximum(vertical, 0.05)),
        "linearity": np.where(l1 > 0, (l1 - l2) / safe, 0.0),
        "planarity": np.where(l1 > 0, (l2 - l3) / safe, 0.0),
        "scattering": np.where(l1 > 0, l3 / safe, 0.0),
        "along_alignment": alignment,
        "verticality": np.abs(e1[:, 2]),
        "normal_z": np.abs(e3[:, 2]),
        "context_count": n_ctx,
    }
    for c, name in enumerate(FEATURE_NAMES):
        out[:, c] = columns[name]
    return out, list(FEATURE_NAMES)
