"""Circle fits for poles and pipe cross-sections (after Fukano & Masuda 2015): algebraic (Kasa),
geometric (Gauss-Newton, optionally with a fixed radius) and robust (RANSAC on 3-point circles,
then the two fits on the inliers). Sparse scans leave a pole a one-sided arc, so a fit also
reports the arc it covers (`arc_span`): how well the points pin the circle down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def fit_circle_algebraic(xy: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Kasa fit: the circle x^2 + y^2 + D x + E y + F = 0 by linear least squares."""
    w = np.ones(len(xy)) if w is None else w
    A = np.column_stack([xy, np.ones(len(xy))]) * w[:, None]
    b = -(xy**2).sum(1) * w
    (D, E, F), *_ = np.linalg.lstsq(A, b, rcond=None)
    c = -0.5 * np.array([D, E])
    return c, float(np.sqrt(max(c @ c - F, 0.0)))


def fit_circle_geometric(
    xy: np.ndarray, c0: np.ndarray, r0: float, iterations: int = 20, radius: float | None = None
) -> tuple[np.ndarray, float]:
    """Gauss-Newton on sum (|p - c| - r)^2 from (c0, r0); with `radius` given, r is held fixed
    (a pole of known radius seen from one side)."""
    c, r = np.asarray(c0, dtype=np.float64).copy(), float(r0 if radius is None else radius)
    for _ in range(iterations):
        v = xy - c
        rho = np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        res = rho - r
        J = -v / rho[:, None]
        if radius is None:
            J = np.column_stack([J, -np.ones(len(xy))])
        step, *_ = np.linalg.lstsq(J, -res, rcond=None)
        c += step[:2]
        if radius is None:
            r += step[2]
        if np.linalg.norm(step) < 1e-7:
            break
    return c, abs(r)


def _circumcircles(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres (m, 2) and radii (m,) of the circles through point triples p (m, 3, 2)."""
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    d = 2.0 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1])
               + c[:, 0] * (a[:, 1] - b[:, 1]))  # fmt: skip
    a2, b2, c2 = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / d
        uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / d
    centre = np.column_stack([ux, uy])
    return centre, np.linalg.norm(centre - a, axis=1)


def arc_span(xy: np.ndarray, c: np.ndarray) -> float:
    """Angle (radians) of the circle around `c` covered by the points (2 pi minus the largest
    angular gap): how well the points pin down a circle."""
    if len(xy) < 2:
        return 0.0
    a = np.sort(np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0]))
    gaps = np.diff(np.r_[a, a[0] + 2.0 * np.pi])
    return float(2.0 * np.pi - gaps.max())


@dataclass
class Circle:
    centre: np.ndarray
    radius: float
    inliers: int
    span: float  # radians of arc covered by the inliers
    rms: float


def fit_circle_ransac(
    xy: np.ndarray,
    rng: np.random.Generator,
    radius_range: tuple[float, float] = (0.015, 0.12),
    inlier_tol: float = 0.01,
    iterations: int = 128,
    min_inliers: int = 8,
) -> Circle | None:
    """Robust circle: the 3-point circle (radius in range) with most points within
    `inlier_tol`, refined by an algebraic then a geometric fit on its inliers. None when no
    plausible circle exists (fewer than 3 points, collinear points)."""
    n = len(xy)
    if n < 3:
        return None
    idx = rng.integers(0, n, size=(iterations, 3)) if n > 3 else np.arange(3)[None]
    idx = idx[(idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])]
    if not len(idx):
        return None
    c, r = _circumcircles(xy[idx])
    ok = np.isfinite(r) & (r >= radius_range[0]) & (r <= radius_range[1])
    if not ok.any():
        return None
    c, r = c[ok], r[ok]
    res = np.abs(np.linalg.norm(xy[None, :, :] - c[:, None, :], axis=2) - r[:, None])
    count = (res < inlier_tol).sum(1)
    best = int(np.argmax(count))
    inl = res[best] < inlier_tol
    if inl.sum() < 3:
        return None
    c1, r1 = fit_circle_algebraic(xy[inl])
    c1, r1 = fit_circle_geometric(xy[inl], c1, r1)
    if not (radius_range[0] <= r1 <= radius_range[1]) or not np.all(np.isfinite(c1)):
        c1, r1 = c[best], float(r[best])
    d = np.abs(np.linalg.norm(xy - c1, axis=1) - r1)
    inl = d < inlier_tol
    q = xy[inl] - xy[inl].mean(0)
    if len(q) < min_inliers or np.ptp(q @ np.linalg.svd(q, full_matrices=False)[2][0]) < 1.5 * r1:
        return None  # the points cover no real chord: a noise blob fits any small circle
    return Circle(
        c1, r1, int(inl.sum()), arc_span(xy[inl], c1), float(np.sqrt((d[inl] ** 2).mean()))
    )
