"""Sliced segments (paper 3.1, Fig. 6): components cut by planes across the trajectory.

Guardrails have any length and may be curved, so each connected component is cut every
`spacing` metres (0.5 m in the paper) of trajectory arc length by planes perpendicular to the
driving direction. A point's slice is (component, floor(station / spacing)); the station and
the signed lateral offset (left of the driving direction positive) come from
`app.geometry.trajectory.StationIndex`, so curves are followed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.geometry.trajectory import StationIndex
from app.pipelines.guardrail.road import as_positions


@dataclass
class SliceSet:
    """K slices of N points. Slice k holds `indices[offsets[k]:offsets[k+1]]` (into xyz_world)."""

    spacing: float
    point_slice: np.ndarray  # (N,) int64 slice of each point, -1 for points in no slice
    indices: np.ndarray  # (M,) int64 point indices grouped by slice
    offsets: np.ndarray  # (K + 1,) int64
    component: np.ndarray  # (K,) int64
    station_index: np.ndarray  # (K,) int64: the slice spans [i, i + 1) * spacing of station
    station: np.ndarray  # (K,) float64 mean station of its points
    centre: np.ndarray  # (K, 3) float64 mean of its points (world)
    lateral: np.ndarray  # (K,) float64 median lateral offset (left positive)
    side: np.ndarray  # (K,) int8 +1 left of the trajectory, -1 right
    direction: np.ndarray  # (K, 2) float64 unit driving direction at the slice (xy)
    point_station: np.ndarray  # (N,) float64 station of every point (nan outside slices)
    point_lateral: np.ndarray  # (N,) float64 lateral offset of every point (nan outside)

    def __len__(self) -> int:
        return len(self.component)

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)

    def points(self, k: int) -> np.ndarray:
        """Point indices of slice k."""
        return self.indices[self.offsets[k] : self.offsets[k + 1]]

    def find(self, component: int, station_index: int) -> int:
        """The slice of (component, station index), -1 when there is none."""
        hit = np.flatnonzero((self.component == component) & (self.station_index == station_index))
        return int(hit[0]) if len(hit) else -1


def cut_slices(
    xyz_world: np.ndarray,
    component: np.ndarray,
    trajectory_positions: np.ndarray,
    spacing: float = 0.5,  # paper: "subdivided at the interval of 0.5 m"
    *,
    min_points: int = 1,
    station_index: StationIndex | None = None,
) -> SliceSet:
    """Cut every component (label >= 0) into slices `spacing` metres long along the trajectory.

    `trajectory_positions`: (M, 3) sensor positions or (M, 4, 4) poses in drive order. Slices
    with fewer than `min_points` points are dropped (their points get slice -1). Slices are
    ordered by (component, station index).
    """
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    xyz = np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3)
    component = np.asarray(component).reshape(-1)
    if len(component) != len(xyz):
        raise ValueError(f"component has {len(component)} entries for {len(xyz)} points")
    n = len(xyz)
    index = (
        StationIndex(as_positions(trajectory_positions)) if station_index is None else station_index
    )
    sel = np.flatnonzero(component >= 0)
    point_station = np.full(n, np.nan)
    point_lateral = np.full(n, np.nan)
    point_slice = np.full(n, -1, dtype=np.int64)
    if len(sel):
        st, lat = index.query(xyz[sel])
        point_station[sel], point_lateral[sel] = st, lat
        sidx = np.floor(st / spacing).astype(np.int64)
        comp = component[sel].astype(np.int64)
        order = np.lexsort((sidx, comp))
        c_o, s_o = comp[order], sidx[order]
        new = np.concatenate([[True], (c_o[1:] != c_o[:-1]) | (s_o[1:] != s_o[:-1])])
        starts = np.flatnonzero(new)
        counts = np.diff(np.append(starts, len(order)))
        big = counts >= min_points
        slice_of_sorted = np.cumsum(new) - 1  # provisional slice id per sorted point
        keep_pt = big[slice_of_sorted]
        renumber = np.cumsum(big) - 1
        order = order[keep_pt]
        slice_of_sorted = renumber[slice_of_sorted[keep_pt]]
        starts, counts = starts[big], counts[big]
        comp_k, sidx_k = c_o[starts], s_o[starts]
        indices = sel[order]
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        point_slice[indices] = slice_of_sorted
        k = len(counts)
        station = np.bincount(slice_of_sorted, point_station[indices], minlength=k) / counts
        origin = xyz[indices].mean(axis=0) if len(indices) else np.zeros(3)
        local = xyz[indices] - origin
        centre = (
            np.stack(
                [np.bincount(slice_of_sorted, local[:, a], minlength=k) for a in range(3)], axis=1
            )
            / counts[:, None]
            + origin
        )
        lateral = _group_median(point_lateral[indices], offsets)
    else:
        indices = np.zeros(0, np.int64)
        offsets = np.zeros(1, np.int64)
        comp_k = sidx_k = np.zeros(0, np.int64)
        station = lateral = np.zeros(0)
        centre = np.zeros((0, 3))
    j = np.clip(np.searchsorted(index.stations, station), 0, len(index.stations) - 1)
    direction = index.directions[j] if len(station) else np.zeros((0, 2))
    return SliceSet(
        spacing=float(spacing),
        point_slice=point_slice,
        indices=indices,
        offsets=offsets,
        component=comp_k,
        station_index=sidx_k,
        station=station,
        centre=centre,
        lateral=lateral,
        side=np.where(lateral > 0, 1, -1).astype(np.int8),
        direction=direction,
        point_station=point_station,
        point_lateral=point_lateral,
    )


def _group_median(values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Median of each group values[offsets[k]:offsets[k+1]] (groups non-empty), vectorised."""
    k = len(offsets) - 1
    if k == 0:
        return np.zeros(0)
    group = np.repeat(np.arange(k), np.diff(offsets))
    order = np.lexsort((values, group))
    v = values[order]
    counts = np.diff(offsets)
    lo = offsets[:-1] + (counts - 1) // 2
    hi = offsets[:-1] + counts // 2
    return 0.5 * (v[lo] + v[hi])
