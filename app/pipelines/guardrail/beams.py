"""Beam reconstruction on the stacked unit shape (Matsumoto, Mori & Masuda, section 4.4).

A W-beam is a bent plate: its section curve, swept along the guardrail, is the whole shape.
Poles (and the block-out spacers that hold the beam off them) are removed, the remaining points
are projected onto the plane perpendicular to the rail (the unit frame's (z, y) plane), cut
into 10 mm horizontal strips, and the centre of each strip becomes a vertex of the section
polyline, smoothed with Taubin's low-pass filter. Assembly sweeps it along the rail.

The paper tells beams from pipes because "a relatively large rectangle region is filled by
points": `looks_like_beam` finds the height cells that most vertical slices of the stacked unit
hold points in; a beam makes a run of them as tall as its plate (~0.3 m), pipes only their
diameter (rails) or nothing (a slanted or vertical pipe occupies few slices per height).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.pipelines.guardrail.config import BandConfig, BeamConfig
from app.pipelines.guardrail.polylines import taubin_smooth


@dataclass
class BeamModel:
    """The beam's section curve in the unit frame: (z, y) = (offset along the plane normal,
    height), bottom to top, for x between the unit's two poles."""

    section: np.ndarray  # (S, 2)
    x_range: tuple[float, float]

    def to_dict(self) -> dict:
        return {
            "section": np.asarray(self.section).tolist(),
            "x_range": [float(v) for v in self.x_range],
        }


def _without_poles(
    points: np.ndarray, pole_x: tuple[float, float], pole_radius: float, margin: float
) -> np.ndarray:
    half = max(pole_radius, 0.075) + margin  # 0.075: half a block-out spacer's length
    keep = np.ones(len(points), dtype=bool)
    for px in pole_x:
        keep &= np.abs(points[:, 0] - px) > half
    xl, xr = sorted(pole_x)
    keep &= (points[:, 0] > xl) & (points[:, 0] < xr)
    return points[keep]


def looks_like_beam(
    points: np.ndarray,
    pole_x: tuple[float, float],
    pole_radius: float,
    config: BandConfig | None = None,
) -> tuple[bool, float]:
    """Whether the stacked unit is a beam (a continuous surface band), and the band height:
    the tallest run of height cells that most (`min_share`) of the occupied vertical slices
    hold points in. A rail fills a few cells in every slice, a slanted or vertical pipe tall
    runs in a few slices only, a beam plate its whole height in nearly every slice."""
    cfg = config or BandConfig()
    slice_width, cell = cfg.slice_width, cfg.cell
    p = _without_poles(points, pole_x, pole_radius, cfg.pole_margin)
    if len(p) < 10:
        return False, 0.0
    sx = np.floor((p[:, 0] - p[:, 0].min()) / slice_width).astype(np.int64)
    cy = np.floor((p[:, 1] - p[:, 1].min()) / cell).astype(np.int64)
    pairs = np.unique(np.column_stack([sx, cy]), axis=0)
    share = np.bincount(pairs[:, 1]) / len(np.unique(sx))
    rows = np.flatnonzero(share >= cfg.min_share)
    if not len(rows):
        return False, 0.0
    brk = np.flatnonzero(np.diff(rows) > cfg.max_gap_cells + 1)
    starts = np.r_[rows[0], rows[brk + 1]]
    ends = np.r_[rows[brk], rows[-1]]
    band = float((ends - starts + 1).max() * cell)
    return band >= cfg.min_band, band


def beam_section(
    points: np.ndarray,
    pole_x: tuple[float, float],
    pole_radius: float,
    config: BeamConfig | None = None,
) -> BeamModel | None:
    """The beam's section polyline from the stacked unit (points (N, 3) in the unit frame),
    or None when no band of points is left."""
    cfg = config or BeamConfig()
    strip, min_strip_points = cfg.strip, cfg.min_strip_points
    p = _without_poles(points, pole_x, pole_radius, cfg.pole_margin)
    if len(p) < 3 * min_strip_points:
        return None
    k = np.floor((p[:, 1] - p[:, 1].min()) / strip).astype(np.int64)
    order = np.argsort(k, kind="stable")
    ks = k[order]
    bounds = np.flatnonzero(np.r_[True, np.diff(ks) != 0, True])
    centres = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b - a < min_strip_points:
            continue
        q = p[order[a:b]]
        centres.append((ks[a], float(np.median(q[:, 2])), float(q[:, 1].mean())))
    if len(centres) < 3:
        return None
    C = np.array(centres)
    # the main band: the longest run of strips without a gap above max_gap
    brk = np.flatnonzero(np.diff(C[:, 0]) * strip > cfg.max_gap)
    starts = np.r_[0, brk + 1]
    ends = np.r_[brk, len(C) - 1]
    i = int(np.argmax(ends - starts))
    C = C[starts[i] : ends[i] + 1]
    section = taubin_smooth(C[:, 1:3], iterations=cfg.taubin_iterations)
    xl, xr = sorted(pole_x)
    return BeamModel(section=section, x_range=(xl, xr))
