"""Pipe reconstruction on the stacked unit shape (Matsumoto, Mori & Masuda, section 4.3).

Everything happens in the reference unit frame (x along the unit, y up, z the plane normal) on
the points projected onto the unit plane (x, y):

1. vertical pipes: peaks of the histogram of x (a threshold that separates continuous regions),
   kept when their points run up the unit; the skeleton is the vertical line at the region's
   centre;
2. the other pipes: with the vertical pipes (and the poles) removed, the points are cut into
   30 mm strips along x, each strip is triangulated (Delaunay), edges longer than a limit are
   dropped, and every connected component gives one centre; centres in neighbouring strips are
   linked into polylines;
3. the polylines are smoothed with Taubin's low-pass filter, fitted with a straight line where
   they are straight (and made horizontal where nearly so), then extended to the poles, vertical
   pipes and each other;
4. the radius of a pipe comes from the points' distances to its skeleton: the band around the
   skeleton that holds a share q of the points is q radii wide each side when the points cover
   the pipe's silhouette evenly (q = 0.5: the inter-quartile range of the signed distances is
   the radius); dense stacks of vertical and slanted pipes, whose band a rotating scanner's
   range noise widens, fit a circle to the pipe's cross-section instead (`pipe_radius`);
5. pipes are swept circles along the skeletons (`meshes.tube`).

Crossing pipes (an X) merge into one component for a few strips; the linking predicts each
polyline's course from its last centres and lets two polylines share the merged centre, so both
pass through the crossing.

Steps 1, 2 and 5 are here; step 3 is `polylines`, step 4 `pipe_radius`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from app.pipelines.guardrail.config import PipeConfig
from app.pipelines.guardrail.pipe_radius import pipe_offsets, pipe_radius
from app.pipelines.guardrail.polylines import (
    drop_duplicates,
    extend_ends,
    merge_collinear,
    straighten,
    taubin_smooth,
)


@dataclass
class Pipe:
    """One pipe of the unit shape: skeleton polyline (K, 3) in the unit frame and radius."""

    polyline: np.ndarray
    radius: float
    kind: str  # "vertical", "horizontal", "straight", "curved"
    points: int = 0  # stacked points that measured its radius

    def to_dict(self) -> dict:
        return {
            "polyline": np.asarray(self.polyline).tolist(),
            "radius": float(self.radius),
            "kind": self.kind,
            "points": int(self.points),
        }


@dataclass
class PipeModel:
    """The pipes of one unit shape (unit frame), between poles at `pole_x`."""

    pipes: list[Pipe] = field(default_factory=list)
    pole_x: tuple[float, float] = (-1.0, 1.0)
    plane_z: float = 0.0

    def to_dict(self) -> dict:
        return {
            "pipes": [p.to_dict() for p in self.pipes],
            "pole_x": [float(v) for v in self.pole_x],
            "plane_z": float(self.plane_z),
        }


# ----------------------------------------------------------------------------- steps


def vertical_pipes(
    xy: np.ndarray,
    x_range: tuple[float, float],
    bin_size: float = 0.01,  # m, histogram of x
    smooth_bins: int = 5,  # box filter over the histogram (scan lines of sparse stacks)
    peak_factor: float = 2.5,  # threshold = factor x the histogram's median level
    min_length: float = 0.3,  # m, a vertical pipe runs at least this far up
    min_coverage: float = 0.6,  # share of 2 cm height bins along it that hold points
    margin: float = 0.015,  # m, added to a region's half-width to remove its points
    min_halfwidth: float = 0.025,  # m, least half-width removed (noisy scans smear pipes)
) -> list[tuple[float, float, float, float]]:
    """Vertical pipes from peaks of the x histogram: (x centre, y low, y high, half-width of
    the region) each. A peak region is kept when its points run up the unit, not when it is
    a pile of scan lines or the steep end of an arc."""
    x0, x1 = x_range
    sel = (xy[:, 0] >= x0) & (xy[:, 0] <= x1)
    if sel.sum() < 10:
        return []
    p = xy[sel]
    edges = np.arange(x0, x1 + bin_size, bin_size)
    h, _ = np.histogram(p[:, 0], edges)
    k = max(1, smooth_bins)
    hs = np.convolve(h, np.ones(k) / k, mode="same")
    level = max(float(np.median(hs)), 1.0)
    above = hs > peak_factor * level
    if not above.any():
        return []
    padded = np.r_[False, above, False].astype(int)
    starts = np.flatnonzero(np.diff(padded) == 1)
    ends = np.flatnonzero(np.diff(padded) == -1)
    out = []
    for a, b in zip(starts, ends, strict=True):
        lo, hi = edges[a], edges[b]
        m = (p[:, 0] >= lo) & (p[:, 0] < hi)
        if m.sum() < 5:
            continue
        xc = float(np.median(p[m, 0]))
        half = 0.5 * (hi - lo)
        win = np.abs(p[:, 0] - xc) <= half
        y = p[win, 1]
        y_lo, y_hi = np.percentile(y, [2, 98])
        if y_hi - y_lo < min_length:
            continue
        bins = np.unique(np.floor((y[(y >= y_lo) & (y <= y_hi)] - y_lo) / 0.02))
        if len(bins) < min_coverage * np.ceil((y_hi - y_lo) / 0.02):
            continue
        out.append((xc, float(y_lo), float(y_hi), max(half, min_halfwidth) + margin))
    return out


def strip_components(xy: np.ndarray, edge_limit: float) -> np.ndarray:
    """Connected components (labels) of the Delaunay triangulation of one strip's points with
    edges longer than `edge_limit` removed. Degenerate strips (fewer than 4 points, all on a
    line) fall back on the edge-limit graph itself, which has the same components."""
    n = len(xy)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    try:
        if n < 4:
            raise QhullError("too few points")
        tri = Delaunay(xy, qhull_options="QJ")
        e = np.concatenate([tri.simplices[:, [0, 1]], tri.simplices[:, [1, 2]],
                            tri.simplices[:, [2, 0]]])  # fmt: skip
    except (QhullError, ValueError):
        e = cKDTree(xy).query_pairs(edge_limit, output_type="ndarray").reshape(-1, 2)
    keep = np.linalg.norm(xy[e[:, 0]] - xy[e[:, 1]], axis=1) <= edge_limit
    e = e[keep]
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def _trace(
    nodes: np.ndarray,
    link_tol: float,
    max_slope: float,
    max_skip: int,
    max_shared: int = 3,
) -> list[list[int]]:
    """Link component centres (rows: strip, x, y, z, count) strip by strip into chains. Each
    open chain predicts its next centre from the line through its last centres; chains and the
    next strip's centres are matched (Hungarian) within `link_tol` of the prediction, and a
    chain left without a centre may share its predicted one for up to `max_shared` strips
    (crossing pipes merge for a few strips; longer sharing is one pipe traced twice)."""
    chains: list[list[int]] = []
    last: list[int] = []  # last strip index per chain
    shared: list[int] = []  # consecutive shared centres at the chain's end
    closed: set[int] = set()
    for k in np.unique(nodes[:, 0]).astype(int):
        cur = np.flatnonzero(nodes[:, 0] == k)
        live = [i for i, s in enumerate(last) if 0 < k - s <= max_skip + 1 and i not in closed]
        C = np.full((len(live), len(cur)), np.inf)
        for a, ci in enumerate(live):
            ch = nodes[chains[ci][-4:]]
            dx = nodes[cur, 1] - ch[-1, 1]
            if len(ch) >= 2 and np.ptp(ch[:, 1]) > 1e-9:
                slope = np.polyfit(ch[:, 1], ch[:, 2], 1)[0]
                pred = ch[-1, 2] + slope * dx
                gate = link_tol * (1.0 + 0.5 * (k - last[ci] - 1))
            else:
                pred = np.full(len(cur), ch[-1, 2])
                gate = link_tol + max_slope * np.abs(dx)
            err = np.abs(nodes[cur, 2] - pred)
            C[a] = np.where(err <= gate, err, np.inf)
        used_nodes: set[int] = set()
        if len(live) and len(cur):
            rows, cols = linear_sum_assignment(np.where(np.isfinite(C), C, 1e6))
            matched = set()
            for r, c in zip(rows, cols, strict=True):
                if np.isfinite(C[r, c]):
                    ci = live[r]
                    chains[ci].append(int(cur[c]))
                    last[ci], shared[ci] = k, 0
                    matched.add(r)
                    used_nodes.add(c)
            for r in range(len(live)):  # share a centre: two pipes crossing
                if r in matched or not np.isfinite(C[r]).any():
                    continue
                ci = live[r]
                if shared[ci] >= max_shared:
                    del chains[ci][len(chains[ci]) - shared[ci] :]
                    closed.add(ci)
                    continue
                c = int(np.argmin(C[r]))
                chains[ci].append(int(cur[c]))
                last[ci] = k
                shared[ci] += 1
                used_nodes.add(c)
        for c in range(len(cur)):
            if c not in used_nodes:
                chains.append([int(cur[c])])
                last.append(k)
                shared.append(0)
    for ci, ch in enumerate(chains):  # a chain never ends on centres it only borrowed
        if shared[ci] and ci not in closed:
            del ch[len(ch) - shared[ci] :]
    return chains


# ----------------------------------------------------------------------------- whole step


def reconstruct_pipes(
    points: np.ndarray,
    pole_x: tuple[float, float],
    pole_radius: float,
    plane_z: float | None = None,
    config: PipeConfig | None = None,
) -> PipeModel:
    """Pipes of the stacked unit (points (N, 3) in the reference unit frame, poles at
    `pole_x`). Skeleton z is `plane_z` (the pole axes' plane: pipes end on the pole axes)
    or, when None, the median z of each pipe's points."""
    cfg = config or PipeConfig()
    P = np.asarray(points, dtype=np.float64)
    xl, xr = sorted(pole_x)
    cut = pole_radius + cfg.pole_margin
    body = P[(P[:, 0] > xl + cut) & (P[:, 0] < xr - cut)]
    model = PipeModel(pole_x=(xl, xr), plane_z=float(plane_z) if plane_z is not None else 0.0)
    if len(body) < 10:
        return model
    z_of = (lambda z: float(plane_z)) if plane_z is not None else (lambda z: float(np.median(z)))

    # 1. vertical pipes
    verts = vertical_pipes(body[:, :2], (xl + cut, xr - cut), min_length=cfg.vertical_min_length)
    rest = np.ones(len(body), dtype=bool)
    vert_lines = []
    for xc, y0, y1, half in verts:
        m = np.abs(body[:, 0] - xc) <= half
        vert_lines.append(np.array([[xc, y0, z_of(body[m, 2])], [xc, y1, z_of(body[m, 2])]]))
        rest &= ~m
    other = body[rest]

    # 2. strips, Delaunay components, centres
    nodes = []
    if len(other):
        sid = np.floor((other[:, 0] - (xl + cut)) / cfg.strip_width).astype(np.int64)
        order = np.argsort(sid, kind="stable")
        bounds = np.flatnonzero(np.r_[True, np.diff(sid[order]) != 0, True])
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            idx = order[a:b]
            lab = strip_components(other[idx, :2], cfg.edge_limit)
            cnt = np.bincount(lab)
            for c in np.flatnonzero(cnt >= cfg.min_component_points):
                q = other[idx[lab == c]]
                nodes.append([sid[idx[0]], q[:, 0].mean(), np.median(q[:, 1]),
                              np.median(q[:, 2]), len(q)])  # fmt: skip
    polys: list[tuple[np.ndarray, str, float]] = []
    if nodes:
        N = np.array(nodes, dtype=np.float64)
        N = N[np.lexsort((N[:, 2], N[:, 0]))]
        for ch in _trace(N, cfg.link_tol, cfg.max_slope, cfg.max_skip):
            if len(ch) < cfg.min_nodes:
                continue
            Q = N[ch][:, 1:4]
            w = N[ch][:, 4]
            Q = taubin_smooth(Q, iterations=cfg.taubin_iterations)
            line, kind = straighten(Q, w, cfg.straight_tol, cfg.snap_deg)
            polys.append((line, kind, float(w.sum())))
    polys = drop_duplicates(
        merge_collinear(polys, cfg.straight_tol, cfg.merge_gap, cfg.snap_deg), cfg.link_tol
    )

    # 3. extend and connect
    y_span = (float(P[:, 1].min()), float(P[:, 1].max()))
    straight = [k != "curved" for _, k, _ in polys]
    lines = extend_ends([p for p, _, _ in polys], straight, vert_lines, (xl, xr), y_span,
                        cfg.connect_dist, cfg.extend_straight)  # fmt: skip
    for V in vert_lines:  # vertical pipes end on the rails they meet
        for end in (0, 1):
            best, y_best = np.inf, None
            for L in lines:
                xs = L[:, 0]
                if xs.min() - 1e-9 <= V[0, 0] <= xs.max() + 1e-9 and len(L) >= 2:
                    o = np.argsort(xs)
                    y = float(np.interp(V[0, 0], xs[o], L[o, 1]))
                    gap = abs(y - V[end, 1])
                    if gap <= cfg.connect_dist and gap < best:
                        best, y_best = gap, y
            if y_best is not None:
                V[end, 1] = y_best

    # 4. radii
    kinds = ["vertical"] * len(vert_lines) + [k for _, k, _ in polys]
    skels = vert_lines + lines
    offs = pipe_offsets(body, skels)
    counts = np.array([len(o) for o in offs], dtype=int)
    radii = np.array(
        [
            pipe_radius(o, k, cfg.radius_share, cfg.dense_points)
            if len(o) >= cfg.min_radius_points
            else np.nan
            for o, k in zip(offs, kinds, strict=True)
        ]
    )
    # a pipe its points cannot measure: the thinnest measured one (inner pipes are no
    # thicker than the rails they hang from)
    fallback = float(np.nanmin(radii)) if np.isfinite(radii).any() else 0.02
    for S, r, n, kind in zip(skels, radii, counts, kinds, strict=True):
        r = fallback if not np.isfinite(r) else float(np.clip(r, *cfg.radius_range))
        S = S.copy()
        if plane_z is not None:
            S[:, 2] = plane_z
        model.pipes.append(Pipe(polyline=S, radius=r, kind=kind, points=int(n)))
    return model
