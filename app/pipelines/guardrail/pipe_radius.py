"""Pipe radii (Matsumoto, Mori & Masuda, section 4.3, step 4): the stacked points go to their
nearest skeleton as (signed offset, depth), and the radius comes from the band they fill (the
paper's rule) or, for dense stacks of vertical and slanted pipes, from a circle fitted to the
pipe's cross-section.
"""

from __future__ import annotations

import numpy as np

from app.pipelines.guardrail.circles import fit_circle_ransac
from app.pipelines.guardrail.polylines import point_segment_distances


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
        D, T, side = point_segment_distances(p, A, B)
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
