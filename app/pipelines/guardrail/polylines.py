"""Pipe skeletons as polylines (Matsumoto, Mori & Masuda, section 4.3, step 3): Taubin's
low-pass filter, a straight line where a polyline is straight (horizontal where nearly so),
pieces of one straight pipe joined, duplicates dropped, and ends extended to the poles, the
vertical pipes and each other. Taubin's filter also smooths the beam's section (`beams`).
"""

from __future__ import annotations

import numpy as np


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


def point_segment_distances(
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


def straighten(
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


def merge_collinear(
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
                line, _ = straighten(pts, w, np.inf, 0.0, min_length=0.0)
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


def drop_duplicates(
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
            d, _, _ = point_segment_distances(smp, Q[:-1], Q[1:])
            if (d.min(1) <= tol).mean() > 0.8:
                dup = True
                break
        if not dup:
            kept.append(i)
    return [polys[i] for i in sorted(kept)]


def extend_ends(
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
