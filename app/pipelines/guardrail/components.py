"""Connected components on the scanner's 2D lattice (paper 3.1, after Kohira & Masuda 2017).

An MMS scanner fires on a regular pattern, so every point has a cell on a 2D lattice; joining
lattice neighbours gives a wireframe of the scanned surfaces, and its connected components are
the roadside objects. Two neighbours are joined only when their 3D distance is within `max_edge`,
so a depth jump (a car in front of a guardrail, a pole in front of a wall) cuts the wireframe.

Lattices (a cell per point, from `scan_points.load_scan_points`): a profile scanner's is one
lattice for the whole drive, a rotating scanner's one per revolution. Consecutive revolutions
see the same objects: a point is also joined to its nearest point of the previous revolution
when that is within `max_edge`.

Neighbourhood: along a row, the next `col_window` cells; across to the next row, columns within
+-`row_col_window`. Wider than the paper's 4-neighbourhood because thin diagonal pipes move
several steps between consecutive profiles and would otherwise break into pieces. Fragments
smaller than `min_points` are attached to the nearest larger component within `attach_distance`.
Points less than `min_height` above the ground (curb faces, sidewalk edges that the road removal
leaves because they are not horizontal) make no edges to higher points and join the component of
the nearest higher point within `max_edge` afterwards: otherwise the curb chains every guardrail
to the cars parked along it (seen on the simulated HDL-64E survey).

**Fallback**: without a lattice (LAS/PLY maps without time, unknown scanner) Euclidean
clustering: points within `cluster_tolerance` are connected, computed on voxel centroids
(voxel = tolerance / 2) with a KD-tree pair search so dense surfaces stay cheap.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from itertools import chain
from typing import Literal

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components as _csgraph_components
from scipy.spatial import cKDTree

from app.pipelines.guardrail.scan_points import Lattice, ScanPoints


@dataclass
class Components:
    """Component id per point (-1: not a candidate, i.e. removed before) and how they were made."""

    label: np.ndarray  # (N,) int32
    count: int
    method: Literal["lattice", "euclidean"]
    sizes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def _lattice_offsets(col_window: int, row_col_window: int) -> np.ndarray:
    """(row, col) offsets to the 'forward' half of the neighbourhood (each edge found once)."""
    along = [(0, c) for c in range(1, col_window + 1)]
    across = [(1, c) for c in range(-row_col_window, row_col_window + 1)]
    return np.array(along + across, dtype=np.int64).reshape(-1, 2)


def wireframe_edges(
    xyz: np.ndarray,
    lattice: Lattice,
    max_edge: float = 0.3,
    col_window: int = 2,
    row_col_window: int = 3,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(i, j) point pairs that are lattice neighbours and within `max_edge` in 3D, a batch per
    neighbour offset (`JoinedComponents` takes them batch by batch: all of them at once, ten
    and more per point, held gigabytes on a tile of four million points).

    Cells are looked up in a dense table (one int per lattice cell) when the lattice is not much
    larger than the point count, else by binary search in the sorted cell keys.
    """
    n = len(xyz)
    if n < 2:
        return
    n_cols = lattice.n_cols
    row0 = int(lattice.row.min())
    n_rows = int(lattice.row.max()) - row0 + 2  # one free row: row + 1 never reaches a sweep
    sweep0 = int(lattice.sweep.min())
    rows = lattice.row - row0
    base = ((lattice.sweep - sweep0) * n_rows + rows) * n_cols
    key = base + lattice.col
    n_keys = (int(lattice.sweep.max()) - sweep0 + 1) * n_rows * n_cols  # free row included

    def close(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        diff = xyz[i] - xyz[j]
        ok = np.einsum("ij,ij->i", diff, diff) <= max_edge**2
        return i[ok], j[ok]

    if n_keys <= max(16 * n, 1 << 24):
        index = np.int32 if n < np.iinfo(np.int32).max else np.int64
        table = np.full(n_keys, -1, dtype=index)
        table[key] = np.arange(n, dtype=index)
        owner = table[key].astype(np.int64)
        dup = np.flatnonzero(owner != np.arange(n))  # cells holding two points: join them
        yield close(dup, owner[dup])

        def lookup(nkey: np.ndarray) -> np.ndarray:
            return table[nkey]

    else:
        order = np.argsort(key, kind="stable")
        skey = key[order]
        same = np.flatnonzero(skey[1:] == skey[:-1])
        yield close(order[same], order[same + 1])

        def lookup(nkey: np.ndarray) -> np.ndarray:
            at = np.minimum(np.searchsorted(skey, nkey), n - 1)
            return np.where(skey[at] == nkey, order[at], -1)

    for dr, dc in _lattice_offsets(col_window, row_col_window):
        nkey = base + dr * n_cols + np.mod(lattice.col + dc, n_cols)
        j = lookup(nkey).astype(np.int64, copy=False)
        src = np.flatnonzero(j >= 0)
        yield close(src, j[src])


def _sweep_edges(
    xyz: np.ndarray, sweep: np.ndarray, max_edge: float
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Each point to its nearest point of the previous sweep, when within max_edge (a batch
    per sweep)."""
    ids = np.unique(sweep)
    groups = {int(s): np.flatnonzero(sweep == s) for s in ids}
    for a, b in zip(ids[:-1], ids[1:], strict=True):
        prev, cur = groups[int(a)], groups[int(b)]
        if len(prev) == 0 or len(cur) == 0:
            continue
        tree = cKDTree(xyz[prev])
        d, nb = tree.query(xyz[cur], k=1, distance_upper_bound=max_edge, workers=-1)
        ok = np.isfinite(d)
        yield cur[ok], prev[nb[ok]]


def euclidean_edges(xyz: np.ndarray, tolerance: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Edges of Euclidean clustering, on voxel centroids: returns (point, point) pairs that tie
    each point to its voxel's first point and voxels whose centroids are within `tolerance`."""
    n = len(xyz)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    voxel = tolerance / 2.0
    local = xyz - np.floor(xyz.min(axis=0) / voxel) * voxel  # whole steps from xyz's origin
    ijk = np.floor(local / voxel).astype(np.int64)
    _, first, inverse = np.unique(ijk, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse)
    centres = np.stack([np.bincount(inverse, local[:, a]) for a in range(3)], axis=1)
    centres /= counts[:, None]
    pairs = cKDTree(centres).query_pairs(tolerance, output_type="ndarray")
    i = np.concatenate([np.arange(n), first[pairs[:, 0]]])
    j = np.concatenate([first[inverse], first[pairs[:, 1]]])
    return i, j


class JoinedComponents:
    """Connected components of `n` points from edges given batch by batch: each batch joins
    the components found so far (its edges taken between them, repeats dropped), so memory is
    that of one batch. A component is known by its smallest point index."""

    def __init__(self, n: int):
        self.root = np.arange(n, dtype=np.int64)

    def add(self, i: np.ndarray, j: np.ndarray) -> None:
        a, b = self.root[i], self.root[j]
        apart = a != b
        if not apart.any():
            return
        a, b = a[apart], b[apart]
        roots, inverse = np.unique(np.concatenate([a, b]), return_inverse=True)
        m = len(a)
        graph = coo_matrix(
            (np.ones(m, dtype=np.int8), (inverse[:m], inverse[m:])), shape=(len(roots),) * 2
        )
        _, group = _csgraph_components(graph, directed=False)
        smallest = np.full(group.max() + 1, len(self.root), dtype=np.int64)
        np.minimum.at(smallest, group, roots)
        to = np.arange(len(self.root), dtype=np.int64)
        to[roots] = smallest[group]
        self.root = to[self.root]

    def labels(self) -> np.ndarray:
        """(n,) int64 component ids, numbered in order of their first point (as scipy's)."""
        return np.unique(self.root, return_inverse=True)[1].reshape(-1).astype(np.int64)


def _attach_fragments(
    xyz: np.ndarray,
    label: np.ndarray,
    min_points: int,
    distance: float,
    eligible: np.ndarray | None = None,
) -> np.ndarray:
    """Fragments smaller than min_points take the label of the nearest larger component within
    `distance` (each fragment as a whole, by its point nearest to one); only `eligible` points
    (default all) take part, as fragments or as targets."""
    sizes = np.bincount(label)
    small = sizes[label] < min_points
    ok_pts = np.ones(len(label), dtype=bool) if eligible is None else eligible
    big = np.flatnonzero(~small & ok_pts)
    frag = np.flatnonzero(small & ok_pts)
    if len(big) == 0 or len(frag) == 0:
        return label
    d, nb = cKDTree(xyz[big]).query(xyz[frag], k=1, distance_upper_bound=distance, workers=-1)
    ok = np.isfinite(d)
    if not ok.any():
        return label
    frag, d, target = frag[ok], d[ok], label[big[nb[ok]]]
    order = np.lexsort((d, label[frag]))  # per fragment, nearest first
    flab = label[frag][order]
    first = np.concatenate([[True], flab[1:] != flab[:-1]])
    mapping = np.arange(len(sizes))
    mapping[flab[first]] = target[order][first]
    return mapping[label]


def _attach_low(xyz: np.ndarray, label: np.ndarray, low: np.ndarray, distance: float) -> np.ndarray:
    """Each low point takes the label of its nearest high point within `distance`."""
    high = np.flatnonzero(~low)
    lows = np.flatnonzero(low)
    d, nb = cKDTree(xyz[high]).query(xyz[lows], k=1, distance_upper_bound=distance, workers=-1)
    ok = np.isfinite(d)
    label = label.copy()
    label[lows[ok]] = label[high[nb[ok]]]
    return label


def connected_components(
    points: ScanPoints | np.ndarray,
    keep: np.ndarray | None = None,
    *,
    lattice: Lattice | None = None,
    max_edge: float = 0.3,  # paper: lattice neighbours are connected (no distance given)
    col_window: int = 2,
    row_col_window: int = 3,
    link_sweeps: bool = True,
    cluster_tolerance: float = 0.3,
    min_points: int = 10,
    attach_distance: float = 0.5,
    above_ground: np.ndarray | None = None,
    min_height: float = 0.25,
    origin: np.ndarray | None = None,
) -> Components:
    """Connected components of the kept points (paper 3.1).

    `points`: `ScanPoints` from `load_scan_points` (its lattice is used) or an (N, 3) world
    array (then `lattice` may be given, else Euclidean clustering). `keep`: (N,) bool, e.g.
    `remove_road(...)`; removed points get label -1. Labels are 0..count-1, largest first.
    `origin` (default: the kept points' mean) anchors the Euclidean clustering's voxels.

    `above_ground` (N,) (e.g. `RoadRemoval.above_ground`): points lower than `min_height` make
    no edges to higher points; each joins the component of its nearest higher point within
    `max_edge`, the rest stay connected among themselves. Without this, curbs and sidewalk
    edges (left by the road removal: not horizontal) chain guardrails to parked cars.
    """
    if isinstance(points, ScanPoints):
        xyz = points.xyz
        lattice = points.lattice if lattice is None else lattice
    else:
        xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n_all = len(xyz)
    sel = np.arange(n_all) if keep is None else np.flatnonzero(keep)
    sub = xyz[sel]
    centre = sub.mean(axis=0) if origin is None and len(sub) else origin
    local = sub - centre if len(sub) else sub
    method: Literal["lattice", "euclidean"] = "lattice" if lattice is not None else "euclidean"
    batches: Iterable[tuple[np.ndarray, np.ndarray]]
    if lattice is not None:
        lat = lattice.take(sel)
        batches = wireframe_edges(local, lat, max_edge, col_window, row_col_window)
        if link_sweeps and lat.kind == "rotating" and len(np.unique(lat.sweep)) > 1:
            batches = chain(batches, _sweep_edges(local, lat.sweep, max_edge))
    else:
        batches = [euclidean_edges(local, cluster_tolerance)]
    low = None
    if above_ground is not None and len(sub):
        low = np.asarray(above_ground, dtype=np.float64)[sel] < min_height
    joined = JoinedComponents(len(sub))
    for i, j in batches:
        if low is not None:  # no edge between a low point and a higher one
            same = low[i] == low[j]
            i, j = i[same], j[same]
        joined.add(i, j)
    label = joined.labels()
    if min_points > 1 and len(sub):
        eligible = None if low is None else ~low  # low points are attached below
        label = _attach_fragments(local, label, min_points, attach_distance, eligible)
    if low is not None and low.any() and not low.all():
        label = _attach_low(local, label, low, max_edge)
    out = np.full(n_all, -1, dtype=np.int32)
    sizes = np.zeros(0, dtype=np.int64)
    if len(sub):
        counts = np.bincount(label)
        used = np.flatnonzero(counts)
        by_size = used[np.argsort(-counts[used], kind="stable")]
        rank = np.full(len(counts), -1, dtype=np.int64)
        rank[by_size] = np.arange(len(by_size))
        out[sel] = rank[label]
        sizes = counts[by_size]
    return Components(out, int(len(sizes)), method, sizes)
