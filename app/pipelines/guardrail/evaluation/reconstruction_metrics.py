"""Reconstruction scores against the simulator's exact guardrail models
(`app.simulate.guardrails`: poles with base / top / radius, pipes as world polylines with
radii, the W-beam as a section curve swept along a world path).

- pole position error: each observable true pole (one with input points within
  `observable_dist` of it) matched to the nearest reconstructed pole within `max_match`; the
  error is the horizontal distance of the centres;
- pipe radius error and recovery: a true pipe is recovered when at least `coverage` of its
  length (sampled every 2 cm) lies within `tol` of a reconstructed pipe's axis; its radius
  error is |reconstructed - true| for the reconstructed pipe nearest to most of it;
- beam section distance: at every reconstructed beam vertex, the reconstructed section is
  expressed in the true beam's cross-section frame there, and the mean distance of each
  curve's points to the other curve is taken both ways (symmetric mean);
- share of pipes recovered against the number of units stacked (the paper: 4 units for simple
  pipes, 25 for diagonal ones).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from app.pipelines.guardrail.config import ReconstructionConfig


def _model(rg: Any) -> dict:
    return rg if isinstance(rg, dict) else rg.model


def _resample(P: np.ndarray, step: float) -> np.ndarray:
    out = [P[:1]]
    for a, b in zip(P[:-1], P[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + np.outer(np.arange(1, n + 1) / n, b - a))
    return np.concatenate(out)


def _seg_dist(p: np.ndarray, A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of points p (n, d) to their nearest segment A->B (m, d), and its index."""
    e = B - A
    w = p[:, None, :] - A[None]
    t = np.clip((w * e[None]).sum(-1) / np.maximum((e**2).sum(-1), 1e-18), 0.0, 1.0)
    d = np.linalg.norm(w - t[..., None] * e[None], axis=-1)
    k = np.argmin(d, axis=1)
    return d[np.arange(len(p)), k], k


def observable_poles(truth: dict, points: np.ndarray | None, observable_dist: float = 0.5):
    """Mask of the true poles that have input points within `observable_dist` (plan)."""
    base = np.array([p["base"] for p in truth["poles"]], dtype=np.float64)
    if points is None or not len(points):
        return np.ones(len(base), dtype=bool)
    d, _ = cKDTree(np.asarray(points)[:, :2]).query(base[:, :2])
    return d <= observable_dist


def pole_errors(
    rg: Any, truth: dict, points: np.ndarray | None = None, max_match: float = 0.5
) -> dict:
    """Horizontal pole position errors (m) of the observable true poles."""
    model = _model(rg)
    tb = np.array([p["base"] for p in truth["poles"]], dtype=np.float64)
    seen = observable_poles(truth, points)
    rec = np.array([p["base"] for p in model["poles"]], dtype=np.float64).reshape(-1, 3)
    detected = np.array([p.get("detected", True) for p in model["poles"]], dtype=bool)
    if not len(rec) or not seen.any():
        return {"errors": [], "median": None, "mean": None, "recall": 0.0, "precision": 0.0,
                "observable": int(seen.sum()), "detected_median": None}  # fmt: skip
    d, j = cKDTree(rec[:, :2]).query(tb[seen, :2])
    ok = d <= max_match
    err = d[ok]
    d_rec, _ = cKDTree(tb[:, :2]).query(rec[:, :2])
    det_err = err[detected[j[ok]]]
    return {
        "errors": err.tolist(),
        "median": float(np.median(err)) if len(err) else None,
        "mean": float(err.mean()) if len(err) else None,
        "recall": float(ok.mean()),
        "precision": float((d_rec <= max_match).mean()),
        "observable": int(seen.sum()),
        "detected_median": float(np.median(det_err)) if len(det_err) else None,
    }


def pipe_errors(
    rg: Any,
    truth: dict,
    points: np.ndarray | None = None,
    tol: float = 0.05,
    coverage: float = 0.8,
    step: float = 0.02,
) -> dict:
    """Recovery and radius errors (m) of the true pipes in observable units (both poles
    observable)."""
    model = _model(rg)
    seen = observable_poles(truth, points)
    true_pipes = [p for p in truth.get("pipes", []) if seen[p["unit"]] and seen[p["unit"] + 1]]
    rec = model.get("pipes") or []
    out = {"pipes": len(true_pipes), "recovered": 0, "recovered_share": 0.0,
           "radius_errors": [], "radius_median": None, "by_role": {}}  # fmt: skip
    if not true_pipes:
        return out
    if rec:
        A = np.concatenate([np.asarray(p["polyline"])[:-1] for p in rec])
        B = np.concatenate([np.asarray(p["polyline"])[1:] for p in rec])
        owner = np.concatenate([np.full(len(p["polyline"]) - 1, i) for i, p in enumerate(rec)])
        mids = 0.5 * (A + B)
        tree = cKDTree(mids)
        reach = float(np.linalg.norm(B - A, axis=1).max()) * 0.5 + tol
    for tp in true_pipes:
        S = _resample(np.asarray(tp["polyline"], dtype=np.float64), step)
        role = tp.get("role", "pipe")
        entry = out["by_role"].setdefault(role, {"pipes": 0, "recovered": 0, "radius_errors": []})
        entry["pipes"] += 1
        if not rec:
            continue
        d = np.full(len(S), np.inf)
        who = np.full(len(S), -1)
        near = tree.query_ball_point(S, reach)
        cand = np.unique(np.concatenate([np.asarray(n, dtype=np.int64) for n in near] + [[]]))
        cand = cand.astype(np.int64)
        if len(cand):
            dd, k = _seg_dist(S, A[cand], B[cand])
            d, who = dd, owner[cand[k]]
        close = d <= tol
        if close.mean() >= coverage:
            out["recovered"] += 1
            entry["recovered"] += 1
            best = np.bincount(who[close]).argmax()
            e = abs(float(rec[best]["radius"]) - float(tp["radius"]))
            out["radius_errors"].append(e)
            entry["radius_errors"].append(e)
    out["recovered_share"] = out["recovered"] / len(true_pipes)
    if out["radius_errors"]:
        out["radius_median"] = float(np.median(out["radius_errors"]))
    return out


def beam_section_distance(rg: Any, truth: dict) -> dict:
    """Distance (m) between the reconstructed and the true beam section at the reconstructed
    path vertices: per vertex the symmetric mean distance of the two curves in the true
    cross-section; reported as the median over vertices (and the worst vertex)."""
    model = _model(rg)
    tb, rb = truth.get("beam"), model.get("beam")
    if not tb or not rb:
        return {"median": None, "max": None, "stations": 0}
    tpath = np.asarray(tb["path"], dtype=np.float64)
    tsec = np.asarray(tb["section"], dtype=np.float64)
    up = np.asarray(tb.get("up", [0.0, 0.0, 1.0]), dtype=np.float64)
    rsec = _resample(np.asarray(rb["section"], dtype=np.float64), 0.005)
    tsec_dense = _resample(tsec, 0.005)
    rpath = np.asarray(rb["path"], dtype=np.float64)
    across = np.asarray(rb["across"], dtype=np.float64)
    rup = np.asarray(rb["up"], dtype=np.float64)
    dists = []
    for P, a, u in zip(rpath, across, rup, strict=True):
        X = P + rsec[:, :1] * a + rsec[:, 1:2] * u  # reconstructed section in world
        _, k = _seg_dist(P[None], tpath[:-1], tpath[1:])
        k = int(k[0])
        d = tpath[k + 1] - tpath[k]
        d /= np.linalg.norm(d)
        left = np.cross(up, d)
        left /= np.linalg.norm(left)
        upv = np.cross(d, left)
        w = X - tpath[k]
        along = w @ d
        if along.min() < -0.5 or along.max() > np.linalg.norm(tpath[k + 1] - tpath[k]) + 0.5:
            continue  # beyond the true beam's ends
        uv = np.column_stack([w @ left, w @ upv])
        d1, _ = _seg_dist(uv, tsec[:-1], tsec[1:])
        d2, _ = _seg_dist(tsec_dense, uv[:-1], uv[1:])
        dists.append(0.5 * (d1.mean() + d2.mean()))
    if not dists:
        return {"median": None, "max": None, "stations": 0}
    return {"median": float(np.median(dists)), "max": float(np.max(dists)),
            "stations": len(dists)}  # fmt: skip


def evaluate_guardrail(rg: Any, truth: dict, points: np.ndarray | None = None) -> dict:
    """All scores of one reconstructed guardrail against its true model."""
    model = _model(rg)
    out = {
        "kind": model.get("kind"),
        "true_kind": truth.get("kind"),
        "units_stacked": model.get("units_stacked"),
        "icp_residual": model.get("icp_residual"),
        "poles": pole_errors(model, truth, points),
    }
    if truth.get("kind") == "pipe":
        out["pipes"] = pipe_errors(model, truth, points)
    if truth.get("kind") == "beam":
        out["beam"] = beam_section_distance(model, truth)
    return out


def pipes_recovered_vs_units(
    points: np.ndarray,
    trajectory: np.ndarray | None,
    truth: dict,
    counts: tuple[int, ...] = (1, 2, 4, 8, 16),
    config: ReconstructionConfig | None = None,
) -> dict[int, float]:
    """Share of the true pipes recovered when only `k` units are stacked, per k (the
    reconstruction, with `config`'s other settings, runs once per k with `max_units=k`)."""
    from app.pipelines.guardrail.reconstruction import reconstruct_guardrail

    out = {}
    for k in counts:
        rg = reconstruct_guardrail(points, trajectory, config, kind="pipe", max_units=k)
        out[int(k)] = pipe_errors(rg, truth, points)["recovered_share"]
        if rg.units_stacked < k:
            break
    return out
