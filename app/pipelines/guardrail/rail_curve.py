"""The guardrail's course (Matsumoto, Mori & Masuda, section 4.1): a smoothed polyline in plan
view through the guardrail's own points, with stations, so that every later step (poles, unit
shapes, posts behind a beam) can address a point as (station along the rail, lateral offset).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import minimum_spanning_tree, shortest_path
from scipy.spatial import Delaunay, QhullError, cKDTree

from app.pipelines.guardrail.config import CurveConfig


@dataclass
class RailCurve:
    """The guardrail's course in plan view: a smoothed polyline through its points, with
    stations (arc length) so points can be addressed as (station s, signed lateral offset d,
    positive to the left of the direction of increasing s)."""

    xy: np.ndarray  # (K, 2) vertices
    stations: np.ndarray  # (K,) arc length at each vertex

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Station and signed lateral offset (n,), (n,) of plan positions `xy` (n, 2)."""
        P, S = self.xy, self.stations
        seg_d = np.diff(P, axis=0)
        seg_l = np.maximum(np.linalg.norm(seg_d, axis=1), 1e-12)
        seg_u = seg_d / seg_l[:, None]
        _, v = cKDTree(P).query(xy, workers=-1)
        best_s = np.zeros(len(xy))
        best_d = np.full(len(xy), np.inf)
        last = len(seg_u) - 1
        for off in (-1, 0):  # the segments before and after the nearest vertex
            j = np.clip(v + off, 0, last)
            w = xy - P[j]
            t = np.einsum("ij,ij->i", w, seg_u[j])
            lo = np.where(j == 0, -np.inf, 0.0)  # the open ends extrapolate
            hi = np.where(j == last, np.inf, seg_l[j])
            t = np.clip(t, lo, hi)
            r = w - t[:, None] * seg_u[j]
            dist = np.linalg.norm(r, axis=1)
            lat = seg_u[j, 0] * r[:, 1] - seg_u[j, 1] * r[:, 0]
            take = dist < np.abs(best_d)
            best_s = np.where(take, S[j] + t, best_s)
            best_d = np.where(take, lat, best_d)
        return best_s, best_d

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Plan positions (n, 2) and unit tangents (n, 2) at stations `s` (extrapolated)."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        P, S = self.xy, self.stations
        j = np.clip(np.searchsorted(S, s, side="right") - 1, 0, len(S) - 2)
        d = P[j + 1] - P[j]
        u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return P[j] + (s - S[j])[:, None] * u, u

    def left(self, s: np.ndarray) -> np.ndarray:
        """Unit normals (n, 2) to the left of the course at stations `s`."""
        _, u = self.at(s)
        return np.column_stack([-u[:, 1], u[:, 0]])


def _diameter_path(xy: np.ndarray) -> np.ndarray:
    """Vertex order along the longest path of the Euclidean minimum spanning tree of `xy`: the
    course of a band-like point set, whatever its curvature."""
    n = len(xy)
    if n < 4:
        return np.argsort(_principal_coordinate(xy))
    try:
        tri = Delaunay(xy, qhull_options="QJ")
        e = np.concatenate([tri.simplices[:, [0, 1]], tri.simplices[:, [1, 2]],
                            tri.simplices[:, [2, 0]]])  # fmt: skip
    except QhullError:
        return np.argsort(_principal_coordinate(xy))
    e = np.unique(np.sort(e, axis=1), axis=0)
    w = np.linalg.norm(xy[e[:, 0]] - xy[e[:, 1]], axis=1) + 1e-9
    mst = minimum_spanning_tree(coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr())
    d0 = shortest_path(mst, directed=False, indices=0)
    a = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
    da, pred = shortest_path(mst, directed=False, indices=a, return_predecessors=True)
    b = int(np.argmax(np.where(np.isfinite(da), da, -1)))
    path = [b]
    while path[-1] != a:
        path.append(int(pred[path[-1]]))
    return np.array(path[::-1])


def _principal_coordinate(xy: np.ndarray) -> np.ndarray:
    c = xy - xy.mean(0)
    if len(xy) < 2:
        return np.zeros(len(xy))
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    return c @ vt[0]


def rail_curve(
    points: np.ndarray, trajectory: np.ndarray | None = None, config: CurveConfig | None = None
) -> RailCurve:
    """The course of the guardrail from its own points (cell centroids ordered along the
    longest path of their spanning tree, smoothed). Oriented like the trajectory when one is
    given (stations grow in the driving direction), else along the first principal axis."""
    cfg = config or CurveConfig()
    cell, smooth, extend = cfg.cell, cfg.smooth, cfg.extend
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    keys = np.floor((xy - xy.min(0)) / cell).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    cent = np.column_stack(
        [np.bincount(inv, xy[:, k], minlength=len(counts)) / counts for k in range(2)]
    )
    order = _diameter_path(cent)
    P = cent[order]
    if len(P) >= 3 and smooth > 1:
        k = min(smooth, len(P) if len(P) % 2 else len(P) - 1)
        pad = k // 2
        Pp = np.concatenate([np.repeat(P[:1], pad, 0), P, np.repeat(P[-1:], pad, 0)])
        kern = np.ones(k) / k
        P = np.column_stack([np.convolve(Pp[:, j], kern, mode="valid") for j in range(2)])
        P[0], P[-1] = cent[order[0]], cent[order[-1]]
    keep = np.r_[True, np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-6]
    P = P[keep]
    if len(P) < 2:  # a single cell: any horizontal direction through it
        P = np.array([P[0] - [0.5 * cell, 0.0], P[0] + [0.5 * cell, 0.0]])
    direction = P[-1] - P[0]
    if trajectory is not None and len(trajectory) >= 2:
        T = np.asarray(trajectory, dtype=np.float64)[:, :2]
        _, i0 = cKDTree(T).query(P[[0, -1]])
        if i0[1] < i0[0] or (i0[1] == i0[0] and direction @ (T[-1] - T[0]) < 0):
            P = P[::-1]
    elif direction @ _principal_axis_sign(xy) < 0:
        P = P[::-1]
    u0 = (P[1] - P[0]) / np.linalg.norm(P[1] - P[0])
    u1 = (P[-1] - P[-2]) / np.linalg.norm(P[-1] - P[-2])
    P = np.concatenate([[P[0] - extend * u0], P, [P[-1] + extend * u1]])
    S = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
    return RailCurve(P, S - extend)


def _principal_axis_sign(xy: np.ndarray) -> np.ndarray:
    """A fixed orientation for the first principal axis (largest |component| positive)."""
    c = xy - xy.mean(0)
    _, _, vt = np.linalg.svd(c[:: max(1, len(c) // 5000)], full_matrices=False)
    v = vt[0]
    return v if v[np.argmax(np.abs(v))] > 0 else -v
