"""How far points are from a guardrail's model (`guardrails`: its JSON-ready parametric model):
`surface_distance`, exact near the guardrail, against pipes and round poles (capped / mitred
cylinder pieces), box posts and spacers, and the swept W-beam sheet, each primitive searched
among the nearest by its centre."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
from scipy.spatial import cKDTree

from app.simulate.meshes import unit_rows

_PIECE = 0.2  # m, longest piece of a pipe / pole in the distance search


def _nearest(
    points: np.ndarray,
    centres: np.ndarray,
    pair_dist: Callable[[np.ndarray, np.ndarray], np.ndarray],
    bound: Callable[[np.ndarray], np.ndarray],
    cutoff: float,
    k0: int = 16,
    chunk_pairs: int = 1 << 19,
) -> np.ndarray:
    """Smallest `pair_dist(point, primitive)` per point over primitives found by their
    `centres`: the k nearest centres first, k growing (x4) for points whose result could still
    be beaten by a primitive outside them (`bound(D_k)` is a lower bound on any primitive whose
    centre is at least D_k away) and is below `cutoff`."""
    N, M = len(points), len(centres)
    out = np.full(N, np.inf)
    if N == 0 or M == 0:
        return out
    tree = cKDTree(centres)
    todo = np.arange(N)
    k = min(k0, M)
    while len(todo):
        dk, ik = tree.query(points[todo], k=k, workers=-1)
        dk, ik = dk.reshape(len(todo), k), ik.reshape(len(todo), k)
        best = np.empty(len(todo))
        step = max(1, chunk_pairs // k)
        for c in range(0, len(todo), step):  # chunks bound the memory of the pair arrays
            p = np.repeat(points[todo[c : c + step]], k, axis=0)
            best[c : c + step] = pair_dist(p, ik[c : c + step].ravel()).reshape(-1, k).min(1)
        out[todo] = best
        if k == M:
            break
        low = bound(dk[:, -1])
        todo = todo[(best > low) & (low < cutoff)]
        k = min(4 * k, M)
    return out


def _solid_pieces(model: dict) -> dict[str, np.ndarray] | None:
    """Pipes and round poles as short capped / mitred cylinder pieces (arrays per piece)."""
    a, b, r, n0, n1, c0, c1 = [], [], [], [], [], [], []
    polys = [(np.asarray(p["polyline"], float), float(p["radius"])) for p in model["pipes"]]
    polys += [
        (np.array([p["base"], p["top"]], float), float(p["radius"]))
        for p in model["poles"]
        if p.get("shape", "round") == "round"
    ]
    for P, rad in polys:
        P = P[np.r_[True, np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-12]]
        d = unit_rows(np.diff(P, axis=0))
        t = np.concatenate([d[:1], unit_rows(d[:-1] + d[1:]), d[-1:]])
        m = len(d)
        a.append(P[:-1])
        b.append(P[1:])
        r.append(np.full(m, rad))
        n0.append(t[:-1])
        n1.append(t[1:])
        c0.append(np.arange(m) == 0)
        c1.append(np.arange(m) == m - 1)
    if not a:
        return None
    A, B = np.concatenate(a), np.concatenate(b)
    R, N0, N1 = np.concatenate(r), np.concatenate(n0), np.concatenate(n1)
    C0, C1 = np.concatenate(c0), np.concatenate(c1)
    # split long segments into pieces of <= _PIECE m (inner cuts: perpendicular, uncapped)
    seg_len = np.linalg.norm(B - A, axis=1)
    n = np.maximum(1, np.ceil(seg_len / _PIECE).astype(int))
    seg = np.repeat(np.arange(len(A)), n)
    k = np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)
    D = unit_rows(B - A)[seg]
    step = (seg_len / n)[seg]
    first, last = k == 0, k == n[seg] - 1
    return {
        "a": A[seg] + (k * step)[:, None] * D,
        "d": D,
        "L": step,
        "r": R[seg],
        "n0": np.where(first[:, None], N0[seg], D),
        "n1": np.where(last[:, None], N1[seg], D),
        "cap0": first & C0[seg],
        "cap1": last & C1[seg],
    }


def _piece_dist(pc: dict[str, np.ndarray], p: np.ndarray, i: np.ndarray) -> np.ndarray:
    """Unsigned distance from points p to the surface of pieces i: lateral surface between the
    two end planes, flat discs at capped ends."""
    a, d, L, r = pc["a"][i], pc["d"][i], pc["L"][i], pc["r"][i]
    cap0, cap1 = pc["cap0"][i], pc["cap1"][i]
    w = p - a
    s = np.einsum("ij,ij->i", w, d)
    rho = np.linalg.norm(w - s[:, None] * d, axis=1)
    lat = np.abs(rho - r)
    out_r = np.maximum(rho - r, 0.0)
    w0 = np.einsum("ij,ij->i", w, pc["n0"][i])
    w1 = np.einsum("ij,ij->i", w - L[:, None] * d, pc["n1"][i])
    res = lat
    disc = rho <= r
    res = np.where(cap0 & disc, np.minimum(res, np.abs(s)), res)
    res = np.where(cap1 & disc, np.minimum(res, np.abs(L - s)), res)
    before = np.where(cap0, np.hypot(out_r, s), np.hypot(lat, w0))
    after = np.where(cap1, np.hypot(out_r, s - L), np.hypot(lat, w1))
    return np.where(w0 < 0.0, before, np.where(w1 > 0.0, after, res))


def _boxes(model: dict) -> dict[str, np.ndarray] | None:
    """Box posts and block-out spacers: centres, half sizes, yaws."""
    c, h, y = [], [], []
    for p in model["poles"]:
        if p.get("shape") == "box":
            base, top = np.asarray(p["base"], float), np.asarray(p["top"], float)
            c.append(0.5 * (base + top))
            h.append(0.5 * np.array([*p["size"], np.linalg.norm(top - base)]))
            y.append(p["yaw"])
    for s in model.get("spacers", []):
        c.append(np.asarray(s["center"], float))
        h.append(0.5 * np.asarray(s["size"], float))
        y.append(s["yaw"])
    if not c:
        return None
    return {"c": np.array(c), "h": np.array(h), "yaw": np.array(y, dtype=np.float64)}


def _box_dist(bx: dict[str, np.ndarray], p: np.ndarray, i: np.ndarray) -> np.ndarray:
    """Unsigned distance from points p to the surface of boxes i."""
    w = p - bx["c"][i]
    cy, sy = np.cos(bx["yaw"][i]), np.sin(bx["yaw"][i])
    q = np.column_stack([cy * w[:, 0] + sy * w[:, 1], -sy * w[:, 0] + cy * w[:, 1], w[:, 2]])
    e = np.abs(q) - bx["h"][i]
    outside = np.linalg.norm(np.maximum(e, 0.0), axis=1)
    return np.where(np.all(e <= 0.0, axis=1), -e.max(1), outside)


def _beam_segments(beam: dict) -> dict[str, np.ndarray]:
    """The swept W-beam as path segments with their section frames and mitre planes."""
    P = np.asarray(beam["path"], float)
    P = P[np.r_[True, np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-12]]
    up = np.asarray(beam.get("up", [0.0, 0.0, 1.0]), float)
    d = unit_rows(np.diff(P, axis=0))
    left = unit_rows(np.cross(up, d))
    t = np.concatenate([d[:1], unit_rows(d[:-1] + d[1:]), d[-1:]])
    return {
        "a": P[:-1],
        "d": d,
        "L": np.linalg.norm(np.diff(P, axis=0), axis=1),
        "left": left,
        "up": np.cross(d, left),
        "n0": t[:-1],
        "n1": t[1:],
        "sec": np.asarray(beam["section"], float),
    }


def _beam_dist(bm: dict[str, np.ndarray], p: np.ndarray, i: np.ndarray) -> np.ndarray:
    """Unsigned distance from points p to the beam sheet over path segments i: distance to the
    section curve in the segment's cross-section, plus how far p lies beyond its mitre planes."""
    w = p - bm["a"][i]
    d, L = bm["d"][i], bm["L"][i]
    uv = np.column_stack(
        [np.einsum("ij,ij->i", w, bm["left"][i]), np.einsum("ij,ij->i", w, bm["up"][i])]
    )
    sec = bm["sec"]
    s0, e = sec[:-1], np.diff(sec, axis=0)  # section segments (S-1, 2)
    rel = uv[:, None, :] - s0[None]
    t = np.clip(np.einsum("nsk,sk->ns", rel, e) / np.einsum("sk,sk->s", e, e), 0.0, 1.0)
    d2 = np.linalg.norm(rel - t[..., None] * e[None], axis=2).min(1)
    w0 = np.einsum("ij,ij->i", w, bm["n0"][i])
    w1 = np.einsum("ij,ij->i", w - L[:, None] * d, bm["n1"][i])
    over = np.maximum(np.maximum(-w0, w1), 0.0)
    return np.hypot(d2, over)


def surface_distance(model: dict, points: np.ndarray, cutoff: float = 1.0) -> np.ndarray:
    """Unsigned distance (N,) from each point to the nearest surface of the guardrail `model`:
    pipes (swept circles, mitred at joints, flat end caps), round poles (capped cylinders), box
    posts and spacers, and the W-beam sheet (section curve swept along its path). Exact for
    points within `cutoff` m of the guardrail; farther points get an upper bound of their
    distance that is itself > cutoff (so thresholds below `cutoff` are safe)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    # per kind of primitive: (centres, distance to primitive i, lower bound of the distance to
    # a primitive whose centre is D away, options of `_nearest`)
    searches: list[tuple[np.ndarray, Callable, Callable, dict]] = []
    pieces = _solid_pieces(model)
    if pieces is not None:
        half = float(0.5 * pieces["L"].max())
        cos_min = float(
            np.minimum(
                np.einsum("ij,ij->i", pieces["n0"], pieces["d"]),
                np.einsum("ij,ij->i", pieces["n1"], pieces["d"]),
            ).min()
        )
        slope = 1.0 + np.sqrt(max(1.0 - cos_min**2, 0.0)) / max(cos_min, 1e-3)
        radius = pieces["r"].max()
        searches.append(
            (
                pieces["a"] + 0.5 * pieces["L"][:, None] * pieces["d"],
                partial(_piece_dist, pieces),
                lambda D: (D - half) / slope - radius,
                {},
            )
        )
    boxes = _boxes(model)
    if boxes is not None:
        box_reach = float(np.linalg.norm(boxes["h"], axis=1).max())
        searches.append((boxes["c"], partial(_box_dist, boxes), lambda D: D - box_reach, {"k0": 4}))
    if model.get("beam"):
        bm = _beam_segments(model["beam"])
        sec_c = bm["sec"].mean(0)
        centres = (
            bm["a"] + 0.5 * bm["L"][:, None] * bm["d"] + sec_c[0] * bm["left"] + sec_c[1] * bm["up"]
        )
        beam_reach = float(
            0.5 * bm["L"].max() + 2.0 * np.linalg.norm(bm["sec"] - sec_c, axis=1).max()
        )
        options = {"k0": 8, "chunk_pairs": 1 << 16}
        searches.append((centres, partial(_beam_dist, bm), lambda D: D - beam_reach, options))
    out = np.full(len(pts), np.inf)
    for centres, pair_dist, bound, options in searches:
        out = np.minimum(out, _nearest(pts, centres, pair_dist, bound, cutoff, **options))
    return out
