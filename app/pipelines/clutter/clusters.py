"""Euclidean clusters of one frame's non-ground points (the 3D expansion works on these).

Ground first (5th-percentile height per cell, `app.geometry.ground`), then connected components
of the occupied `voxel`-sized voxels with 26-neighbourhood: two points share a cluster when a
chain of occupied voxels links them, which is Euclidean clustering with a tolerance of about one
voxel, computed with one sort and a sparse-graph labelling instead of a radius search per point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from app.geometry.ground import estimate_ground
from app.geometry.voxels import voxel_indices

# half of the 26 neighbours: each undirected voxel edge is found once
_HALF_NEIGHBOURS = np.array(
    [
        (i, j, k)
        for i in (-1, 0, 1)
        for j in (-1, 0, 1)
        for k in (-1, 0, 1)
        if (i, j, k) > (0, 0, 0)
    ],
    dtype=np.int64,
)


@dataclass
class FrameClusters:
    """Cluster id per point (-1: ground or out of range) and the height above the ground."""

    label: np.ndarray  # (N,) int32
    above_ground: np.ndarray  # (N,) float64 metres

    @property
    def count(self) -> int:
        return int(self.label.max()) + 1 if len(self.label) else 0


def voxel_components(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """(N,) int32 component id per point: connected occupied voxels (26-neighbourhood)."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.int32)
    ijk = voxel_indices(xyz, voxel)
    ijk -= ijk.min(axis=0) - 1  # a free layer on every side: neighbours never wrap
    dims = ijk.max(axis=0) + 2
    keys = np.ravel_multi_index(tuple(ijk.T), tuple(dims))
    occupied, point_voxel = np.unique(keys, return_inverse=True)
    cells = np.stack(np.unravel_index(occupied, tuple(dims)), axis=1)
    rows, cols = [], []
    for offset in _HALF_NEIGHBOURS:
        neighbour = np.ravel_multi_index(tuple((cells + offset).T), tuple(dims))
        at = np.searchsorted(occupied, neighbour)
        at[at == len(occupied)] = 0
        hit = occupied[at] == neighbour
        rows.append(np.flatnonzero(hit))
        cols.append(at[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(len(occupied),) * 2)
    _, voxel_label = connected_components(graph, directed=False)
    return voxel_label[point_voxel.reshape(-1)].astype(np.int32)


def frame_clusters(
    xyz: np.ndarray,
    voxel: float,
    ground_cell: float,
    ground_tolerance: float,
    max_range: float,
    subset: np.ndarray | None = None,
) -> FrameClusters:
    """Clusters of the points more than `ground_tolerance` above the ground, within range;
    with `subset` (bool per point) only of those points, on the ground of all of them."""
    label = np.full(len(xyz), -1, dtype=np.int32)
    above = np.zeros(len(xyz))
    if len(xyz) == 0:
        return FrameClusters(label, above)
    ground = estimate_ground(xyz, cell=ground_cell)
    above = xyz[:, 2] - ground.height(xyz)
    near = np.einsum("ij,ij->i", xyz[:, :2], xyz[:, :2]) <= max_range**2
    objects = near & (above > ground_tolerance)
    if subset is not None:
        objects &= subset
    objects = np.flatnonzero(objects)
    label[objects] = voxel_components(xyz[objects], voxel)
    return FrameClusters(label, above)


# metres: the grid cells by which `object_hosts` finds the points near its objects' boxes
NEAR_CELL = 1.0


def object_hosts(
    xyz: np.ndarray,
    label: np.ndarray,
    trackable: np.ndarray,
    near_ground: np.ndarray,
    ground_radius: float,
    fragment_radius: float,
    ground_angle: float = 0.0,
) -> np.ndarray:
    """(N,) int32: the trackable cluster each loose point belongs to (-1: none, and -1 for the
    points of trackable clusters themselves).

    A far car breaks into pieces (windows return nothing, 0.4 m voxels do not bridge the gaps
    between sparse scan lines), and its wheels' lowest points fall within the ground's
    tolerance; the tracker follows the largest piece. Pieces too small to track take the
    cluster of their nearest point's trackable neighbour within `fragment_radius`; points at
    ground level (`near_ground`) only within `ground_radius` (tyres, not the road around them),
    or `ground_angle` radians of the scanner's view where that is wider (`xyz` in sensor
    coordinates): a far car's lowest scan line lies a beam's spacing below its body's.
    """
    host = np.full(len(xyz), -1, dtype=np.int32)
    clustered = label >= 0
    anchored = clustered & trackable[np.where(clustered, label, 0)]
    if not anchored.any():
        return host
    anchors = np.flatnonzero(anchored)
    anchors = anchors[np.argsort(label[anchors], kind="stable")]
    lower, upper = _boxes(xyz[anchors], label[anchors])
    tree = None
    for loose, radius, angle in (
        (clustered & ~anchored, fragment_radius, 0.0),
        (~clustered & near_ground, ground_radius, ground_angle),
    ):
        if max(radius, angle) <= 0 or not loose.any():
            continue
        at = np.flatnonzero(loose)
        at = at[_near_boxes(xyz[at], lower, upper, radius, angle)]  # the tree's candidates
        if not len(at):
            continue
        reach = np.full(len(at), radius)
        if angle > 0:
            reach = np.maximum(radius, angle * np.linalg.norm(xyz[at], axis=1))
        tree = cKDTree(xyz[anchors]) if tree is None else tree
        distance, nearest = tree.query(xyz[at], k=1, distance_upper_bound=float(reach.max()))
        found = distance <= reach
        host[at[found]] = label[anchors[nearest[found]]]
    return host


def _boxes(xyz: np.ndarray, label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C, 3) lower and upper corners of each cluster's points (`label` sorted, C clusters)."""
    starts = np.flatnonzero(np.r_[True, label[1:] != label[:-1]])
    return np.minimum.reduceat(xyz, starts), np.maximum.reduceat(xyz, starts)


def _near_boxes(
    xyz: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    radius: float,
    angle: float,
    cell: float = NEAR_CELL,
) -> np.ndarray:
    """(N,) bool: the points that may lie within max(`radius`, `angle` x their range) of a
    box's contents: those in the `cell`-metre grid cells (horizontal) that the boxes, grown
    by that reach, touch (a superset: cells and boxes, not points). Most of a frame lies far
    from its few trackable objects; this spares the tree their queries. A point within
    `angle` x its range r of a box whose farthest corner lies at c has r <= c + angle x r, so
    its reach there is at most angle x c / (1 - angle)."""
    if angle >= 1.0:
        return np.ones(len(xyz), dtype=bool)
    corner = np.linalg.norm(np.maximum(np.abs(lower), np.abs(upper)), axis=1)
    margin = np.maximum(radius, angle * corner / (1.0 - angle))[:, None]
    first = np.floor((lower[:, :2] - margin) / cell).astype(np.int64)
    last = np.floor((upper[:, :2] + margin) / cell).astype(np.int64)
    origin = first.min(axis=0)
    touched = np.zeros(last.max(axis=0) - origin + 1, dtype=bool)
    for (i0, j0), (i1, j1) in zip(first - origin, last - origin, strict=True):  # per box
        touched[i0 : i1 + 1, j0 : j1 + 1] = True
    ij = np.floor(xyz[:, :2] / cell).astype(np.int64) - origin
    on = np.flatnonzero(((ij >= 0) & (ij < touched.shape)).all(axis=1))
    inside = np.zeros(len(xyz), dtype=bool)
    inside[on] = touched[ij[on, 0], ij[on, 1]]
    return inside
