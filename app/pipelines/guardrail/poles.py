"""Pole detection (Matsumoto, Mori & Masuda, section 4.1, after Fukano & Masuda 2015).

The guardrail points are cut by horizontal section planes; in every section the points are
grouped along the rail, and groups that are compact (narrower than a pole) are fitted with
circles. Circles that line up vertically form a cylinder: a pole. Its height runs from the
ground (lowest point) to its highest point. What makes a pole and not a vertical pipe is that it
stands on the ground: its column reaches the lowest guardrail points around it.

Sparse scans (a profile scanner at speed hits a 7 cm pole once, or not at all) leave poles with
a one-sided arc or a single scan line. So the circle fit is robust (RANSAC on 3-point circles,
then an inlier least-squares fit), poles share one radius (a guardrail uses one pole type), a
pole whose own arc cannot fix its radius is fitted with the shared radius behind its visible
side, and gaps of whole unit lengths get poles inferred from the spacing. (The circle fits are
`circles`, the rail's course `rail_curve`.)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from app.pipelines.guardrail.circles import Circle, fit_circle_geometric, fit_circle_ransac
from app.pipelines.guardrail.config import PoleConfig
from app.pipelines.guardrail.rail_curve import RailCurve, rail_curve


@dataclass
class Pole:
    """A cylindrical pole: plan centre, radius, ground (base) and top heights."""

    centre: np.ndarray  # (2,) world xy
    radius: float
    base: float  # ground height under the pole (z)
    top: float  # height of its highest point (z)
    station: float  # along the rail curve
    points: int  # points of its column (0 when inferred)
    detected: bool = True  # False: inferred in a gap from the pole spacing
    fitted: bool = False  # True when its own arc fixed the circle (not the shared radius)
    support: np.ndarray | None = field(default=None, repr=False)  # (n, 2) plan points
    away: np.ndarray | None = field(default=None, repr=False)  # sensor -> pole, unit (2,)

    @property
    def base_point(self) -> np.ndarray:
        return np.array([self.centre[0], self.centre[1], self.base])

    @property
    def top_point(self) -> np.ndarray:
        return np.array([self.centre[0], self.centre[1], self.top])

    def to_dict(self) -> dict:
        return {
            "base": self.base_point.tolist(),
            "top": self.top_point.tolist(),
            "radius": float(self.radius),
            "station": float(self.station),
            "points": int(self.points),
            "detected": bool(self.detected),
        }


@dataclass
class _Column:
    """Compact section clusters that line up vertically: a pole or vertical pipe candidate."""

    members: np.ndarray  # point indices (the column's core)
    station: float
    offset: float
    z_min: float
    z_max: float
    sections: int
    ground: float  # lowest guardrail point around it
    under: float  # lowest point of the long structures (rails, beam) around it; inf if none


def scan_spacing(s: np.ndarray, bin_size: float = 0.02, max_gap: float = 1.0) -> float:
    """Typical along-rail distance between scan lines: a profile scanner cuts the rail in
    lines one profile apart (10-25 cm at road speeds), a rotating scanner fills it densely.
    The 90th percentile of the gaps between occupied `bin_size` bins (occlusions excluded)."""
    b = np.unique(np.floor(s / bin_size).astype(np.int64))
    g = np.diff(b) * bin_size
    g = g[g < max_gap]
    return float(np.percentile(g, 90)) if len(g) else bin_size


def _section_blobs(
    s: np.ndarray, z: np.ndarray, section_step: float, cluster_gap: float, max_pole_width: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per point: its section index and the id of its compact cluster in that section (-1 if
    its cluster is wider than a pole along the rail: a rail, a beam)."""
    sec = np.floor((z - z.min()) / section_step).astype(np.int64)
    order = np.lexsort((s, sec))
    ss, sc = s[order], sec[order]
    new = np.r_[True, (np.diff(sc) != 0) | (np.diff(ss) > cluster_gap)]
    run = np.cumsum(new) - 1
    first = np.flatnonzero(new)
    last = np.r_[first[1:] - 1, len(ss) - 1]
    compact = ss[last] - ss[first] <= max_pole_width
    blob = np.full(len(s), -1, dtype=np.int64)
    blob[order] = np.where(compact[run], run, -1)
    return sec, blob


def _window_min(s_sorted: np.ndarray, z_sorted: np.ndarray, centre: float, half: float) -> float:
    lo, hi = np.searchsorted(s_sorted, [centre - half, centre + half])
    return float(z_sorted[lo:hi].min()) if hi > lo else float("inf")


def _columns(
    s: np.ndarray,
    d: np.ndarray,
    z: np.ndarray,
    section_step: float,
    cluster_gap: float,
    max_pole_width: float,
    column_tol: float,
    ground_window: float,
    core_halfwidth: float,
) -> list[_Column]:
    """Vertically aligned compact section clusters, grouped by their (station, offset), each
    cut down to its core around the station of its lowest sections (where a pole stands alone;
    higher up a diagonal leaving the pole can join its clusters)."""
    sec, blob = _section_blobs(s, z, section_step, cluster_gap, max_pole_width)
    sel = np.flatnonzero(blob >= 0)
    if not len(sel):
        return []
    ids, inv, cnt = np.unique(blob[sel], return_inverse=True, return_counts=True)
    inv = inv.ravel()
    bs = np.bincount(inv, s[sel]) / cnt
    bd = np.bincount(inv, d[sel]) / cnt
    pairs = cKDTree(np.column_stack([bs, bd])).query_pairs(column_tol, output_type="ndarray")
    n = len(ids)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    ncomp, comp = connected_components(g, directed=False)
    point_comp = comp[inv]
    order = np.argsort(point_comp, kind="stable")
    bounds = np.searchsorted(point_comp[order], np.arange(ncomp + 1))
    o_all = np.argsort(s)
    s_all, z_all = s[o_all], z[o_all]
    long_pts = np.flatnonzero(blob < 0)
    o_long = long_pts[np.argsort(s[long_pts])]
    s_long, z_long = s[o_long], z[o_long]
    cols = []
    for k in range(ncomp):
        members = sel[order[bounds[k] : bounds[k + 1]]]
        low = members[sec[members] <= sec[members].min() + 2]
        sc, dc = float(np.median(s[low])), float(np.median(d[low]))
        members = members[
            (np.abs(s[members] - sc) <= core_halfwidth) & (np.abs(d[members] - dc) <= column_tol)
        ]
        if not len(members):
            continue
        sc = float(np.median(s[members]))
        cols.append(
            _Column(
                members=members,
                station=sc,
                offset=float(np.median(d[members])),
                z_min=float(z[members].min()),
                z_max=float(z[members].max()),
                sections=len(np.unique(sec[members])),
                ground=_window_min(s_all, z_all, sc, ground_window),
                under=_window_min(s_long, z_long, sc, 0.5),
            )
        )
    return cols


def _fit_pole_circle(
    xy: np.ndarray,
    z: np.ndarray,
    rng: np.random.Generator,
    section_step: float,
    radius_range: tuple[float, float],
    inlier_tol: float,
    min_span: float,
    iterations: int,
) -> Circle | None:
    """The paper's circles per horizontal section, then their vertically aligned consensus:
    sections whose centres agree with the median centre are pooled into one fit (the axis is
    vertical, so all sections share the centre)."""
    sec = np.floor((z - z.min()) / section_step).astype(np.int64)
    centres, good = [], []
    for k in np.unique(sec):
        m = sec == k
        if m.sum() < 5:
            continue
        c = fit_circle_ransac(xy[m], rng, radius_range, inlier_tol, iterations)
        if c is not None and c.span >= min_span and c.inliers >= 0.6 * m.sum():
            centres.append(c.centre)
            good.append(k)
    if centres:
        med = np.median(np.array(centres), axis=0)
        aligned = [k for k, c in zip(good, centres, strict=True) if np.linalg.norm(c - med) < 0.03]
        pool = np.isin(sec, aligned)
        pooled = fit_circle_ransac(xy[pool], rng, radius_range, inlier_tol, iterations)
        if pooled is not None and pooled.span >= min_span:
            return pooled
    whole = fit_circle_ransac(xy, rng, radius_range, inlier_tol, iterations)
    if whole is not None and whole.span >= min_span and whole.inliers >= 0.6 * len(xy):
        return whole
    return None


def _away_direction(
    xy: np.ndarray, trajectory: np.ndarray | None, circle: Circle | None
) -> np.ndarray | None:
    """Horizontal unit vector from the sensor towards the pole: the pole's centre lies behind
    its visible side. From the trajectory, else from a (radius-unreliable) circle fit."""
    m = xy.mean(0)
    if trajectory is not None and len(trajectory):
        T = np.asarray(trajectory, dtype=np.float64)[:, :2]
        v = m - T[np.argmin(np.linalg.norm(T - m, axis=1))]
    elif circle is not None:
        v = circle.centre - m
    else:
        return None
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else None


def detect_poles(
    points: np.ndarray,
    trajectory: np.ndarray | None = None,
    curve: RailCurve | None = None,
    config: PoleConfig | None = None,
) -> list[Pole]:
    """Poles of one guardrail from its points (N, 3) world, sorted along the rail (the
    direction of travel when the trajectory is given)."""
    cfg = config or PoleConfig()
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 10:
        return []
    curve = curve if curve is not None else rail_curve(pts, trajectory)
    s, d = curve.project(pts[:, :2])
    z = pts[:, 2]
    rng = np.random.default_rng(cfg.seed)
    # sections of a rail must join across scan lines, whatever the scanner's line spacing
    gap = max(cfg.cluster_gap, 1.5 * scan_spacing(s))
    cols = _columns(s, d, z, cfg.section_step, gap, max(cfg.max_pole_width, gap), cfg.column_tol,
                    cfg.ground_window, cfg.core_halfwidth)  # fmt: skip
    cand = [
        c
        for c in cols
        if c.sections >= cfg.min_sections
        and c.z_max - c.z_min >= cfg.min_pole_height
        and c.z_min - c.ground <= cfg.ground_tol
        and c.z_min <= c.under - cfg.below_rails
    ]
    if not cand:
        return []
    circles = []
    for c in cand:
        circles.append(
            _fit_pole_circle(
                pts[c.members, :2],
                z[c.members],
                rng,
                cfg.section_step,
                cfg.radius_range,
                cfg.inlier_tol,
                cfg.min_arc,
                cfg.ransac_iterations,
            )  # fmt: skip
        )
    fitted = [c.radius for c in circles if c is not None]
    shared = float(np.median(fitted)) if fitted else cfg.radius_prior
    plan = cKDTree(pts[:, :2])
    poles = []
    for c, circ in zip(cand, circles, strict=True):
        xy = pts[c.members, :2]
        own = circ is not None and abs(circ.radius - shared) <= 0.25 * shared
        pole = Pole(centre=xy.mean(0), radius=shared, base=c.z_min, top=c.z_max,
                    station=c.station, points=len(c.members), detected=True,
                    fitted=bool(own), support=xy,
                    away=_away_direction(xy, trajectory, circ))  # fmt: skip
        if own:
            pole.centre, pole.radius = circ.centre, circ.radius
        else:
            _place(pole, shared)
        # the highest point of the pole: anything above its footprint (top rail included)
        near = plan.query_ball_point(pole.centre, pole.radius + 0.03)
        pole.top = float(z[near].max()) if len(near) else c.z_max
        poles.append(pole)
    poles.sort(key=lambda p: p.station)
    poles = _drop_off_spacing(poles)
    if cfg.infer_missing and len(poles) >= 2:
        poles = _infer_missing(poles, curve, s, trajectory)
    return poles


def _place(pole: Pole, radius: float, depth_factor: float = 0.8) -> None:
    """Centre of a pole whose own arc does not fix its circle, given the radius: a fixed-radius
    circle fit when its points span a chord of at least one radius, else its visible points'
    centroid pushed `depth_factor` radii away from the sensor (the mean depth of a
    cylinder's visible side is pi/4 of its radius; a box post's face lies deeper)."""
    pole.radius = radius
    xy = pole.support
    if xy is None or not len(xy):
        return
    m = xy.mean(0)
    if pole.away is None:
        pole.centre = m
        return
    across = np.array([-pole.away[1], pole.away[0]])
    c0 = m + depth_factor * radius * pole.away
    pole.centre = c0
    if np.ptp(xy @ across) >= radius:
        c, _ = fit_circle_geometric(xy, m + radius * pole.away, radius, radius=radius)
        if np.linalg.norm(c - c0) <= radius:
            pole.centre = c


def place_poles(poles: list[Pole], radius: float) -> None:
    """Give every pole whose own arc did not fix its circle `radius` and re-place its centre
    (e.g. once the guardrail kind is known and its pole-size prior applies)."""
    for p in poles:
        if not p.fitted:
            _place(p, radius)


def pole_spacing(
    poles: list[Pole],
    spacing_range: tuple[float, float] = (0.8, 6.0),  # m, plausible unit lengths
    tol: float = 0.15,  # m, a gap "is" k units when within this of k * L
    inlier_share: float = 0.75,  # share of gaps that must be whole numbers of units
    max_units: int = 3,  # a gap counts as at most this many units (two poles missed in a row)
) -> float:
    """Unit length: the longest L (on a 1 cm grid) for which most pole gaps (weighted by the
    support of their weaker pole) are whole multiples of L (missed poles make gaps of 2 L,
    3 L; a spurious pole makes an odd one), refined as the median of gap / k over them. A gap
    of more than `max_units` units is no evidence for L: any short L divides a long gap nearly
    evenly, and a spurious pole 0.8 m from a real one once made 0.8 m "explain" gaps of 3.2 and
    4 m (and the pipe guardrail between 2 m poles came out a beam)."""
    g = np.diff([p.station for p in poles])
    support = np.array([max(p.points, 1) * max(p.top - p.base, 0.01) for p in poles])
    w = np.minimum(support[:-1], support[1:])  # a gap is as trustworthy as its weaker pole
    w, g = w[g > 0.0], g[g > 0.0]
    if not len(g):
        return float("nan")
    L = np.arange(spacing_range[0], spacing_range[1] + 1e-9, 0.01)
    k = np.maximum(1.0, np.round(g[None, :] / L[:, None]))
    ok = (np.abs(g[None, :] - k * L[:, None]) <= tol) & (k <= max_units)
    good = np.flatnonzero((ok * w).sum(1) >= inlier_share * w.sum())
    if not len(good):
        return float(np.median(g))
    i = good[-1]
    return float(np.median(g[ok[i]] / k[i, ok[i]]))


def _drop_off_spacing(poles: list[Pole], tol: float = 0.2) -> list[Pole]:
    """Detections whose gaps to both neighbours are no whole number of units are spurious
    (a column at the data's edge, a vertical pipe); also, of two poles closer than 0.6 units,
    the less supported one goes."""
    for _ in range(len(poles)):
        if len(poles) < 3:
            break
        L = pole_spacing(poles)
        st = np.array([p.station for p in poles])
        g = np.diff(st)
        off = np.abs(g - np.maximum(1.0, np.round(g / L)) * L) > tol
        off |= g < 0.6 * L
        bad_prev = np.r_[True, off]  # gap to the previous pole is off (or there is none)
        bad_next = np.r_[off, True]
        bad = np.flatnonzero(bad_prev & bad_next)
        if not len(bad):
            break
        score = np.array([poles[i].points * (poles[i].top - poles[i].base) for i in bad])
        poles.pop(int(bad[np.argmin(score)]))
    return poles


def _infer_missing(
    poles: list[Pole], curve: RailCurve, s_all: np.ndarray, trajectory: np.ndarray | None
) -> list[Pole]:
    """Poles in gaps of k >= 2 unit lengths, and beyond the ends while the guardrail's points
    go on for most of a unit: plan position on the rail course at the detected poles' lateral
    offset, the median pole height, and a base that follows the road: the trajectory's height
    there plus the height above it of the detected poles (interpolated), or without a
    trajectory the bases themselves interpolated."""
    L = pole_spacing(poles)
    if not np.isfinite(L) or L <= 0:
        return poles
    st = np.array([p.station for p in poles])
    centres = np.array([p.centre for p in poles])
    _, lat = curve.project(centres)
    off = float(np.median(lat))
    height = float(np.median([p.top - p.base for p in poles if p.detected]))
    radius = float(np.median([p.radius for p in poles]))
    if trajectory is not None and len(trajectory):
        T = np.asarray(trajectory, dtype=np.float64)
        tree = cKDTree(T[:, :2])

        def road(xy: np.ndarray) -> np.ndarray:
            return T[tree.query(xy)[1], 2]
    else:

        def road(xy: np.ndarray) -> np.ndarray:
            return np.zeros(len(xy))

    rel = np.array([p.base for p in poles]) - road(centres)  # base above the road
    new_s = []
    for i in range(len(poles) - 1):
        k = int(round((st[i + 1] - st[i]) / L))
        new_s += [st[i] + j / k * (st[i + 1] - st[i]) for j in range(1, k)]
    lo, hi = np.percentile(s_all, [0.5, 99.5])
    x = st[0] - L
    while x >= lo - 0.3 * L:
        new_s.append(x)
        x -= L
    x = st[-1] + L
    while x <= hi + 0.3 * L:
        new_s.append(x)
        x += L
    if not new_s:
        return poles
    new_s = np.array(new_s)
    xy, _ = curve.at(new_s)
    xy = xy + off * curve.left(new_s)
    if trajectory is not None and len(trajectory):
        base = road(xy) + np.interp(new_s, st, rel)
    else:  # linear between neighbours, the end slope beyond the ends
        slope = (rel[-1] - rel[0]) / max(st[-1] - st[0], 1e-9)
        base = np.interp(new_s, st, rel)
        base = np.where(new_s < st[0], rel[0] + slope * (new_s - st[0]), base)
        base = np.where(new_s > st[-1], rel[-1] + slope * (new_s - st[-1]), base)
    for sv, b, c in zip(new_s, base, xy, strict=True):
        poles.append(Pole(centre=c, radius=radius, base=float(b), top=float(b) + height,
                          station=float(sv), points=0, detected=False))  # fmt: skip
    poles.sort(key=lambda p: p.station)
    return poles
