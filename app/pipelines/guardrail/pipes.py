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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from app.pipelines.guardrail.poles import fit_circle_ransac


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


# ----------------------------------------------------------------------------- polylines


def taubin_smooth(
    P: np.ndarray,
    lam: float = 0.5,  # Taubin (1995): shrink step lambda
    mu: float = -0.53,  # ... and inflate step mu (pass-band k_PB = 1/lam + 1/mu ~ 0.1)
    iterations: int = 10,
    fix_ends: bool = True,
) -> np.ndarray:
    """Taubin's lambda|mu low-pass filter on an open polyline (K, d): alternating Laplacian
    steps that smooth without the shrinking of plain Laplacian smoothing."""
    Q = np.asarray(P, dtype=np.float64).copy()
    if len(Q) < 3:
        return Q
    for _ in range(iterations):
        for f in (lam, mu):
            L = np.zeros_like(Q)
            L[1:-1] = 0.5 * (Q[:-2] + Q[2:]) - Q[1:-1]
            if not fix_ends:
                L[0], L[-1] = Q[1] - Q[0], Q[-2] - Q[-1]
            Q = Q + f * L
    return Q


def _line_fit(P: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted total-least-squares line through 2D points: centre, unit direction, largest
    perpendicular distance of the points."""
    w = np.ones(len(P)) if w is None else w
    c = (P * w[:, None]).sum(0) / w.sum()
    C = ((P - c) * w[:, None]).T @ (P - c) / w.sum()
    _, V = np.linalg.eigh(C)
    d = V[:, -1]
    if d[0] < 0 or (d[0] == 0 and d[1] < 0):
        d = -d
    perp = np.abs((P - c) @ np.array([-d[1], d[0]]))
    return c, d, float(perp.max())


def _ray_hit(o: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Ray o + t d against segment a + u (b - a): (t, u); (inf, nan) when parallel."""
    e = b - a
    den = d[0] * (-e[1]) - d[1] * (-e[0])
    if abs(den) < 1e-12:
        return np.inf, np.nan
    r = a - o
    t = (r[0] * (-e[1]) - r[1] * (-e[0])) / den
    u = (d[0] * r[1] - d[1] * r[0]) / den
    return float(t), float(u)


def _point_segment_distances(
    p: np.ndarray, A: np.ndarray, B: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For points p (n, 2) and segments A->B (m, 2): distances (n, m), parameters t (n, m)
    clamped to [0, 1], signed side (n, m) (positive left of A->B)."""
    e = B - A
    ee = np.maximum((e**2).sum(1), 1e-18)
    w = p[:, None, :] - A[None]
    t = np.clip((w * e[None]).sum(2) / ee, 0.0, 1.0)
    r = w - t[..., None] * e[None]
    side = e[None, :, 0] * w[..., 1] - e[None, :, 1] * w[..., 0]
    return np.linalg.norm(r, axis=2), t, np.sign(side)


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


def _straighten(
    P: np.ndarray,
    w: np.ndarray,
    straight_tol: float,
    snap_deg: float,
    min_share: float = 0.8,
    min_length: float = 0.25,
) -> tuple[np.ndarray, str]:
    """A straight line over the polyline's extent where it is straight: a line fitted to its
    centres, refitted to those within `straight_tol`, holds at least `min_share` of them (a
    crossing or a junction pulls a few centres off a straight pipe), and is at least
    `min_length` long (a short piece of an arc is straight too). Made horizontal when it is
    within `snap_deg` of horizontal."""
    if np.linalg.norm(P[-1, :2] - P[0, :2]) < min_length:
        return P, "curved"
    inl = np.ones(len(P), dtype=bool)
    for _ in range(3):
        if inl.sum() < 2:
            return P, "curved"
        c, d, _ = _line_fit(P[inl, :2], w[inl])
        dev = np.abs((P[:, :2] - c) @ np.array([-d[1], d[0]]))
        inl = dev <= straight_tol
    if inl.mean() < min_share or inl.sum() < 2:
        return P, "curved"
    t = (P[:, :2] - c) @ d
    ends = c + np.outer([t.min(), t.max()], d)
    kind = "straight"
    if abs(np.degrees(np.arctan2(d[1], d[0]))) <= snap_deg:
        ends[:, 1] = (P[inl, 1] * w[inl]).sum() / w[inl].sum()
        kind = "horizontal"
    z = float(np.median(P[:, 2]))
    return np.column_stack([ends, [z, z]]), kind


def _merge_collinear(
    polys: list[tuple[np.ndarray, str, float]], tol: float, max_gap: float, angle_deg: float
) -> list[tuple[np.ndarray, str, float]]:
    """Join pieces of one straight pipe (cut by a vertical pipe's removal, an occlusion, or
    too short to count as straight on their own) onto a straight line: every point of the
    other piece within `tol` of the line, the two nearly parallel when both are straight, and
    a gap along the line up to `max_gap`."""
    polys = list(polys)
    merged = True
    while merged:
        merged = False
        order = sorted(range(len(polys)), key=lambda i: -polys[i][2])
        for i in order:
            A, ka, wa = polys[i]
            if ka == "curved":
                continue
            da = (A[-1, :2] - A[0, :2]) / max(np.linalg.norm(A[-1, :2] - A[0, :2]), 1e-9)
            n = np.array([-da[1], da[0]])
            for j in range(len(polys)):
                if j == i:
                    continue
                B, kb, wb = polys[j]
                if kb != "curved":
                    db = (B[-1, :2] - B[0, :2]) / max(np.linalg.norm(B[-1, :2] - B[0, :2]), 1e-9)
                    if abs(da @ db) < np.cos(np.radians(angle_deg)):
                        continue
                if np.abs((B[:, :2] - A[0, :2]) @ n).max() > tol:
                    continue
                ta, tb = np.sort(A[:, :2] @ da), np.sort(B[:, :2] @ da)
                if max(tb[0] - ta[-1], ta[0] - tb[-1]) > max_gap:
                    continue
                pts = np.concatenate([A, B])
                w = np.r_[np.full(len(A), wa / len(A)), np.full(len(B), wb / len(B))]
                line, _ = _straighten(pts, w, np.inf, 0.0, min_length=0.0)
                if ka == "horizontal":
                    line[:, 1] = (pts[:, 1] * w).sum() / w.sum()
                polys[i] = (line, ka, wa + wb)
                polys.pop(j)
                merged = True
                break
            if merged:
                break
    return polys


def _sample(P: np.ndarray, step: float = 0.01) -> np.ndarray:
    """Points every `step` along a 2D polyline."""
    out = [P[:1]]
    for a, b in zip(P[:-1], P[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + np.outer(np.arange(1, n + 1) / n, b - a))
    return np.concatenate(out)


def _drop_duplicates(
    polys: list[tuple[np.ndarray, str, float]], tol: float
) -> list[tuple[np.ndarray, str, float]]:
    """Of two polylines running together (most of one within `tol` of the other) keep the
    one better supported."""
    order = sorted(range(len(polys)), key=lambda i: -polys[i][2])
    kept: list[int] = []
    for i in order:
        smp = _sample(polys[i][0][:, :2])
        dup = False
        for j in kept:
            Q = polys[j][0][:, :2]
            d, _, _ = _point_segment_distances(smp, Q[:-1], Q[1:])
            if (d.min(1) <= tol).mean() > 0.8:
                dup = True
                break
        if not dup:
            kept.append(i)
    return [polys[i] for i in sorted(kept)]


def _extend_ends(
    polys: list[np.ndarray],
    straight: list[bool],
    verticals: list[np.ndarray],
    pole_x: tuple[float, float],
    y_span: tuple[float, float],
    connect_dist: float,
    extend_straight: float,
) -> list[np.ndarray]:
    """Extend each polyline end along its direction to the first pole axis, vertical pipe or
    other polyline it meets within `connect_dist` (`extend_straight` for straight lines, whose
    direction is known well; an overshoot of up to 3 cm is trimmed); then pairs of still free
    ends that are close are extended to their lines' intersection."""
    targets: list[tuple[np.ndarray, np.ndarray, int]] = []  # segments (a, b, owner)
    for px in pole_x:
        targets.append((np.array([px, y_span[0] - 1.0]), np.array([px, y_span[1] + 1.0]), -1))
    for V in verticals:
        targets.append((V[0, :2] - [0.0, connect_dist], V[-1, :2] + [0.0, connect_dist], -2))
    out = [P.copy() for P in polys]
    free: list[tuple[int, int]] = []
    for i, P in enumerate(out):
        segs = targets + [
            (Q[k, :2], Q[k + 1, :2], j)
            for j, Q in enumerate(out)
            if j != i
            for k in range(len(Q) - 1)
        ]
        reach = extend_straight if straight[i] else connect_dist
        for end in (0, -1):
            tip = P[end, :2]
            prev = P[1 if end == 0 else -2, :2]
            d = tip - prev
            if np.linalg.norm(d) < 1e-9:
                continue
            d = d / np.linalg.norm(d)
            best = np.inf
            for a, b, _ in segs:
                t, u = _ray_hit(tip, d, a, b)
                if -0.03 <= t <= reach and -1e-9 <= u <= 1.0 + 1e-9 and t < best:
                    best = t
            if np.isfinite(best):
                P[end, :2] = tip + best * d
            else:
                free.append((i, end))
    used = set()
    for a in range(len(free)):
        for b in range(a + 1, len(free)):
            (i, ei), (j, ej) = free[a], free[b]
            if i == j or free[a] in used or free[b] in used:
                continue
            Pi, Pj = out[i], out[j]
            ti, tj = Pi[ei, :2], Pj[ej, :2]
            if np.linalg.norm(ti - tj) > connect_dist:
                continue
            di = ti - Pi[1 if ei == 0 else -2, :2]
            dj = tj - Pj[1 if ej == 0 else -2, :2]
            di /= max(np.linalg.norm(di), 1e-9)
            dj /= max(np.linalg.norm(dj), 1e-9)
            A = np.column_stack([di, -dj])
            if abs(np.linalg.det(A)) > 1e-6:
                s, t = np.linalg.solve(A, tj - ti)
                if -0.03 <= s <= connect_dist and -0.03 <= t <= connect_dist:
                    meet = ti + s * di
                    Pi[ei, :2] = meet
                    Pj[ej, :2] = meet
                    used.update({free[a], free[b]})
                    continue
            meet = 0.5 * (ti + tj)  # nearly parallel: meet half way
            Pi[ei, :2] = meet
            Pj[ej, :2] = meet
            used.update({free[a], free[b]})
    return out


def pipe_offsets(
    points: np.ndarray,
    skeletons: list[np.ndarray],
    assign_dist: float = 0.05,  # m, points farther from every skeleton measure no pipe
) -> list[np.ndarray]:
    """Per skeleton, its points as (signed plan distance from the skeleton, depth z) (n, 2):
    each point goes to its nearest skeleton; points near two skeletons (junctions) and beyond
    a skeleton's ends are left out."""
    xy = points[:, :2]
    A, B, owner = [], [], []
    for i, S in enumerate(skeletons):
        A.append(S[:-1, :2])
        B.append(S[1:, :2])
        owner.append(np.full(len(S) - 1, i))
    out: list[list[np.ndarray]] = [[] for _ in skeletons]
    if not A or not len(xy):
        return [np.zeros((0, 2)) for _ in skeletons]
    A, B, owner = np.concatenate(A), np.concatenate(B), np.concatenate(owner)
    first_seg = np.r_[True, owner[1:] != owner[:-1]]
    last_seg = np.r_[owner[1:] != owner[:-1], True]
    step = max(1, 2_000_000 // max(len(A), 1))
    for c0 in range(0, len(xy), step):  # chunks bound the (points x segments) arrays
        p = xy[c0 : c0 + step]
        z = points[c0 : c0 + step, 2]
        D, T, side = _point_segment_distances(p, A, B)
        per = np.full((len(p), len(skeletons)), np.inf)
        for i in range(len(skeletons)):
            per[:, i] = np.where(owner == i, D, np.inf).min(1)
        best = np.argmin(per, axis=1)
        rows = np.arange(len(p))
        dmin = per[rows, best]
        second = np.partition(per, 1, axis=1)[:, 1] if len(skeletons) > 1 else np.inf
        seg = np.argmin(np.where(owner[None, :] == best[:, None], D, np.inf), axis=1)
        t = T[rows, seg]
        inside = ~((first_seg[seg] & (t <= 0.0)) | (last_seg[seg] & (t >= 1.0)))
        ok = (dmin <= assign_dist) & (second > assign_dist) & inside
        signed = dmin * side[rows, seg]
        for i in range(len(skeletons)):
            m = ok & (best == i)
            if m.any():
                out[i].append(np.column_stack([signed[m], z[m]]))
    return [np.concatenate(o) if o else np.zeros((0, 2)) for o in out]


def radius_from_offsets(offsets: np.ndarray, share: float = 0.5) -> float:
    """The paper's rule: the band around the skeleton holding a share q of the points is q
    radii wide each side when the points cover the silhouette evenly (q = 0.5: IQR)."""
    lo, hi = np.percentile(offsets, [50.0 * (1.0 - share), 50.0 * (1.0 + share)])
    return float(0.5 * (hi - lo) / share)


def pipe_radius(
    offsets: np.ndarray,
    kind: str,
    share: float = 0.5,
    dense_points: int = 2000,  # from this many points on, slanted pipes use the circle fit
    circle_tol: float = 0.005,  # m, RANSAC inlier distance of the cross-section circle
    seed: int = 0,
) -> float:
    """Radius of one pipe from its points as (signed offset, depth).

    Horizontal pipes, and all pipes of sparse stacks: the paper's band rule
    (`radius_from_offsets`, q = `share`); scanners' range noise is mostly horizontal, the
    offsets of horizontal pipes vertical, and a profile scanner's noise lies in its scan plane,
    across the rail. (A vertical pipe crossed by only a few profile lines is not covered
    evenly and comes out too thin, by up to ~8 mm on 7-unit stacks.) Vertical and slanted
    pipes of dense stacks (a rotating scanner: 2 cm range noise, which
    widens their band by several mm): a RANSAC circle fitted to the cross-section (offset,
    depth), which keeps to the less noisy points (simulated HDL-64 stacks: 0.4-1.5 mm error
    against 5-8 mm for the band rule)."""
    if kind == "horizontal" or len(offsets) < dense_points:
        return radius_from_offsets(offsets[:, 0], share)
    c = fit_circle_ransac(offsets, np.random.default_rng(seed), (0.004, 0.08), circle_tol, 256)
    return c.radius if c is not None else radius_from_offsets(offsets[:, 0], share)


# ----------------------------------------------------------------------------- whole step


def reconstruct_pipes(
    points: np.ndarray,
    pole_x: tuple[float, float],
    pole_radius: float,
    plane_z: float | None = None,
    pole_margin: float = 0.03,  # m beyond the pole radius removed with the poles
    strip_width: float = 0.03,  # m, the paper's 30 mm strips along x
    edge_limit: float = 0.04,  # m, longest Delaunay edge inside one pipe's points
    min_component_points: int = 2,
    link_tol: float = 0.03,  # m, a centre joins a polyline this close to its predicted course
    max_slope: float = 2.0,  # steepest first step of a new polyline (dy / dx)
    max_skip: int = 4,  # empty strips a polyline may bridge (sparse scan lines)
    min_nodes: int = 4,  # shorter polylines are noise
    taubin_iterations: int = 10,
    straight_tol: float = 0.02,  # m, a polyline this close to its fitted line is straight
    snap_deg: float = 5.0,  # lines within this of horizontal become horizontal pipes
    merge_gap: float = 0.3,  # m, gap between two pieces of one straight pipe
    connect_dist: float = 0.15,  # m, ends extend this far to meet poles, pipes, each other
    extend_straight: float = 0.35,  # m, ... straight lines this far
    radius_share: float = 0.5,  # q of `radius_from_offsets`
    dense_points: int = 2000,  # see `pipe_radius`
    min_radius_points: int = 15,  # fewer points take the median radius of the other pipes
    radius_range: tuple[float, float] = (0.005, 0.08),  # m
    vertical_min_length: float = 0.3,  # m
) -> PipeModel:
    """Pipes of the stacked unit (points (N, 3) in the reference unit frame, poles at
    `pole_x`). Skeleton z is `plane_z` (the pole axes' plane: pipes end on the pole axes)
    or, when None, the median z of each pipe's points."""
    P = np.asarray(points, dtype=np.float64)
    xl, xr = sorted(pole_x)
    cut = pole_radius + pole_margin
    body = P[(P[:, 0] > xl + cut) & (P[:, 0] < xr - cut)]
    model = PipeModel(pole_x=(xl, xr), plane_z=float(plane_z) if plane_z is not None else 0.0)
    if len(body) < 10:
        return model
    z_of = (lambda z: float(plane_z)) if plane_z is not None else (lambda z: float(np.median(z)))

    # 1. vertical pipes
    verts = vertical_pipes(body[:, :2], (xl + cut, xr - cut), min_length=vertical_min_length)
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
        sid = np.floor((other[:, 0] - (xl + cut)) / strip_width).astype(np.int64)
        order = np.argsort(sid, kind="stable")
        bounds = np.flatnonzero(np.r_[True, np.diff(sid[order]) != 0, True])
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            idx = order[a:b]
            lab = strip_components(other[idx, :2], edge_limit)
            cnt = np.bincount(lab)
            for c in np.flatnonzero(cnt >= min_component_points):
                q = other[idx[lab == c]]
                nodes.append([sid[idx[0]], q[:, 0].mean(), np.median(q[:, 1]),
                              np.median(q[:, 2]), len(q)])  # fmt: skip
    polys: list[tuple[np.ndarray, str, float]] = []
    if nodes:
        N = np.array(nodes, dtype=np.float64)
        N = N[np.lexsort((N[:, 2], N[:, 0]))]
        for ch in _trace(N, link_tol, max_slope, max_skip):
            if len(ch) < min_nodes:
                continue
            Q = N[ch][:, 1:4]
            w = N[ch][:, 4]
            Q = taubin_smooth(Q, iterations=taubin_iterations)
            line, kind = _straighten(Q, w, straight_tol, snap_deg)
            polys.append((line, kind, float(w.sum())))
    polys = _drop_duplicates(_merge_collinear(polys, straight_tol, merge_gap, snap_deg), link_tol)

    # 3. extend and connect
    y_span = (float(P[:, 1].min()), float(P[:, 1].max()))
    lines = _extend_ends([p for p, _, _ in polys], [k != "curved" for _, k, _ in polys],
                         vert_lines, (xl, xr), y_span, connect_dist, extend_straight)  # fmt: skip
    for V in vert_lines:  # vertical pipes end on the rails they meet
        for end in (0, 1):
            best, y_best = np.inf, None
            for L in lines:
                xs = L[:, 0]
                if xs.min() - 1e-9 <= V[0, 0] <= xs.max() + 1e-9 and len(L) >= 2:
                    o = np.argsort(xs)
                    y = float(np.interp(V[0, 0], xs[o], L[o, 1]))
                    gap = abs(y - V[end, 1])
                    if gap <= connect_dist and gap < best:
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
            pipe_radius(o, k, radius_share, dense_points) if len(o) >= min_radius_points else np.nan
            for o, k in zip(offs, kinds, strict=True)
        ]
    )
    # a pipe its points cannot measure: the thinnest measured one (inner pipes are no
    # thicker than the rails they hang from)
    fallback = float(np.nanmin(radii)) if np.isfinite(radii).any() else 0.02
    for S, r, n, kind in zip(skels, radii, counts, kinds, strict=True):
        r = fallback if not np.isfinite(r) else float(np.clip(r, *radius_range))
        S = S.copy()
        if plane_z is not None:
            S[:, 2] = plane_z
        model.pipes.append(Pipe(polyline=S, radius=r, kind=kind, points=int(n)))
    return model
