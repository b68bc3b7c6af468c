"""Unit shapes (Matsumoto, Mori & Masuda, sections 4.1-4.2): the guardrail points between two
consecutive poles, each in its own plane frame.

The frame follows the paper's figure 13: z is the normal of the unit's plane (principal
component analysis of its points, kept horizontal since poles stand vertical), y is the pole
direction (up), x runs along the unit towards the next pole, and the origin is the centre of the
unit's rectangle: half way between the two poles, half way up them, on the points' plane. On a
slope x follows the line between the two pole bases, so the frame is sheared (y stays vertical
like the poles): a sloping unit is then the same shape as a level one, as guardrails are built.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.pipelines.guardrail.config import UnitConfig
from app.pipelines.guardrail.poles import Pole
from app.pipelines.guardrail.rail_curve import RailCurve

_Z = np.array([0.0, 0.0, 1.0])


@dataclass
class UnitFrame:
    """world = origin + x * ex + y * ey + z * ez (ey vertical, ez horizontal, ex may slope)."""

    origin: np.ndarray  # (3,)
    ex: np.ndarray  # (3,) unit, towards the next pole, along the slope
    ez: np.ndarray  # (3,) unit, horizontal plane normal (left of ex)
    ey: np.ndarray = field(default_factory=lambda: _Z.copy())  # (3,) up: the pole direction

    @property
    def matrix(self) -> np.ndarray:
        """4x4 affine map local -> world."""
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = self.ex, self.ey, self.ez, self.origin
        return M

    def to_world(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        return self.origin + q[..., :1] * self.ex + q[..., 1:2] * self.ey + q[..., 2:3] * self.ez

    def to_local(self, p: np.ndarray) -> np.ndarray:
        A = np.column_stack([self.ex, self.ey, self.ez])
        return np.linalg.solve(A, (np.asarray(p, dtype=np.float64) - self.origin).T).T


@dataclass
class Unit:
    """One unit shape: the points between poles `poles[0]` and `poles[1]` (indices into the
    guardrail's pole list), in world and in the unit frame."""

    index: int
    poles: tuple[int, int]
    indices: np.ndarray  # into the guardrail's points
    frame: UnitFrame
    local: np.ndarray  # (n, 3) points in the unit frame
    length: float  # m, between the two pole bases
    height: float  # m, mean pole height (rectangle height)
    pole_local: np.ndarray  # (2, 3) the two pole base points in the unit frame


def plane_normal(points: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Horizontal normal of the points' plane (smallest principal direction of their plan
    positions), oriented like `fallback`; `fallback` when the points do not fix it."""
    xy = points[:, :2] - points[:, :2].mean(0)
    if len(xy) < 10:
        return fallback
    w, V = np.linalg.eigh(xy.T @ xy / len(xy))
    if w[1] < 4.0 * w[0]:  # no elongated plan: the plane is undetermined
        return fallback
    n = np.array([V[0, 0], V[1, 0], 0.0])
    return n if n @ fallback >= 0.0 else -n


def unit_frame(
    a: Pole,
    b: Pole,
    points: np.ndarray | None,
    plane_offset: float | None = None,
    height: float | None = None,
) -> tuple[UnitFrame, float, float]:
    """Frame of the unit between poles a and b (and its length and height). With `points` the
    plane normal and offset come from them (PCA); else the normal is perpendicular to the pole
    line and the origin lies `plane_offset` (default 0) in front of the pole axes. `height`
    (default: the two poles' mean) places the origin half way up."""
    pa, pb = a.base_point, b.base_point
    d = pb - pa
    length = float(np.linalg.norm(d))
    ex = d / max(length, 1e-9)
    flat = np.cross(_Z, ex)
    flat /= max(np.linalg.norm(flat), 1e-9)
    ez = flat if points is None else plane_normal(points, flat)
    ex = ex - (ex @ ez) * ez
    ex /= np.linalg.norm(ex)
    if height is None:
        height = 0.5 * ((a.top - a.base) + (b.top - b.base))
    mid = 0.5 * (pa + pb) + 0.5 * height * _Z
    if points is not None and len(points):
        offset = float(np.median((points - mid) @ ez))
    else:
        offset = 0.0 if plane_offset is None else plane_offset
    return UnitFrame(mid + offset * ez, ex, ez), length, height


def split_units(
    points: np.ndarray,
    poles: list[Pole],
    curve: RailCurve,
    config: UnitConfig | None = None,
) -> list[Unit]:
    """Unit shapes between consecutive poles (sorted along `curve`): each unit's points are
    those whose station lies between its two poles, the poles included."""
    cfg = config or UnitConfig()
    pts = np.asarray(points, dtype=np.float64)
    s, _ = curve.project(pts[:, :2])
    # one rectangle height for all units (the guardrail's pole height), so a pole whose top
    # was not seen does not shift its unit's origin
    tall = [p.top - p.base for p in poles if p.detected] or [p.top - p.base for p in poles]
    height = float(np.median(tall)) if tall else 1.0
    order = np.argsort(s)
    s_sorted = s[order]
    units = []
    for j in range(len(poles) - 1):
        a, b = poles[j], poles[j + 1]
        lo, hi = np.searchsorted(
            s_sorted,
            [a.station - a.radius - cfg.pole_margin, b.station + b.radius + cfg.pole_margin],
        )
        idx = np.sort(order[lo:hi])
        if len(idx) < cfg.min_points:
            continue
        frame, length, _ = unit_frame(a, b, pts[idx], height=height)
        units.append(
            Unit(
                index=j,
                poles=(j, j + 1),
                indices=idx,
                frame=frame,
                local=frame.to_local(pts[idx]),
                length=length,
                height=height,
                pole_local=frame.to_local(np.stack([a.base_point, b.base_point])),
            )  # fmt: skip
        )
    return units
