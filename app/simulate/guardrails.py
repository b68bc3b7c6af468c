"""The guardrail paper's two guardrail kinds, built along a ground line, with their exact models.

Matsumoto, Mori & Masuda build guardrails from identical *unit shapes* between poles: pipe
guardrails (a top rail plus a repeated pattern of thin pipes, often a municipal design) and beam
guardrails (a W-beam section swept along the rail, on posts). The simulator needs both as a
triangle mesh (for ray casting, each triangle labelled PIPE / BEAM / POLE) and as a JSON-ready
parametric model (the ground truth the reconstruction is scored against and that
`surface_distance` measures points against).

Conventions:
- `line` is the guardrail's ground line (K, 3) in world coordinates, z = ground height; poles
  and posts stand on it.
- Poles are spaced so that the straight 3D distance between consecutive pole bases is exactly
  the spacing (on the line's polyline), so every unit has the same length and, on level
  ground, units are rigid copies of each other; on a 40 m radius curve this differs from
  arc-length spacing by < 0.1 mm. The last partial unit is dropped.
- Unit frame: origin at the unit's first pole base, x towards the next pole base, z up (poles
  are vertical), y = z cross x (left). Pipe-guardrail pipes lie in the unit's xz-plane.
- Road side: the road is on the LEFT of the line's direction by default (`road_side="left"`),
  as for `objects.facade`. Beam guardrails hang the W-beam on the road side of the posts; pipe
  guardrails are planar and only record the side.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from app.core.labels import Part
from app.simulate.meshes import box, cylinder, sweep_profile, tube
from app.simulate.scene import Mesh

W_BEAM_DEPTH = 0.311  # m, AASHTO M180 W-beam: height of the section
W_BEAM_CORRUGATION = 0.083  # m, depth of its two corrugations
_Z = np.array([0.0, 0.0, 1.0])
_ARC_STEP = np.radians(6.0)  # bent pipes: at most 6 degrees per polyline segment
_BEAM_STEP = 0.5  # m, longest beam path segment (follows curves)
_PIECE = 0.2  # m, longest piece of a pipe / pole in the distance search


@dataclass
class Guardrail:
    """A guardrail: world-coordinate mesh (part per triangle) and its JSON-ready model."""

    mesh: Mesh
    model: dict


# ----------------------------------------------------------------------------- ground line


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0.0, n, 1.0)


def _stations(line: np.ndarray) -> np.ndarray:
    """Arc length (K,) at each vertex of a polyline."""
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))]


def _at(line: np.ndarray, S: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points (n, 3) of the polyline at arc lengths `s`."""
    return np.stack([np.interp(s, S, line[:, k]) for k in range(3)], -1)


def _clean_line(line: np.ndarray) -> np.ndarray:
    L = np.asarray(line, dtype=np.float64).reshape(-1, 3)
    keep = np.r_[True, np.linalg.norm(np.diff(L, axis=0), axis=1) > 1e-9]
    L = L[keep]
    if len(L) < 2:
        raise ValueError("a guardrail line needs at least two distinct points")
    return L


def pole_stations(line: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) on `line` whose consecutive straight distances are exactly `spacing`,
    starting at its first point, and their arc lengths (n,) along it. The walk is sequential:
    a loop over poles, each step vectorised over the line's vertices."""
    L = _clean_line(line)
    S = _stations(L)
    p, s, j = L[0], 0.0, 0  # current point, its station, the segment it lies on
    pts, sts = [p], [s]
    while True:
        dist = np.linalg.norm(L[j + 1 :] - p, axis=1)
        far = np.flatnonzero(dist >= spacing)
        if not len(far):
            break
        m = j + 1 + int(far[0])
        A, sA = (p, s) if m == j + 1 else (L[m - 1], S[m - 1])
        e, f = L[m] - A, A - p
        ee, fe, ff = e @ e, f @ e, f @ f
        t = (-fe + np.sqrt(max(fe * fe - ee * (ff - spacing**2), 0.0))) / ee
        t = min(max(t, 0.0), 1.0)
        p, s, j = A + t * e, sA + t * np.sqrt(ee), m - 1
        pts.append(p)
        sts.append(s)
    return np.array(pts), np.array(sts)


def _unit_frames(bases: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per unit: x axis (towards the next pole base, may slope) and horizontal left axis."""
    ex = _unit(np.diff(bases, axis=0))
    ey = _unit(np.cross(_Z, ex))
    return ex, ey


# ----------------------------------------------------------------------------- pipe guardrails

PIPE_DESIGNS = ("simple", "diagonal", "curved")


def _arc(x0: float, x1: float, h0: float, sag: float) -> np.ndarray:
    """Circular arc (n, 2) in unit (x, h) from (x0, h0) to (x1, h0) through (mid, h0 - sag)
    (sag < 0: an arch rising above the ends), at most `_ARC_STEP` per segment."""
    a, s = 0.5 * (x1 - x0), abs(sag)
    R = (a * a + s * s) / (2.0 * s)
    phi = np.arctan2(a, R - s)
    n = max(6, int(np.ceil(2.0 * phi / _ARC_STEP)))
    psi = np.linspace(-phi, phi, n + 1)
    sign = 1.0 if sag > 0 else -1.0
    cx, ch = 0.5 * (x0 + x1), h0 - sign * (s - R)
    pts = np.column_stack([cx + R * np.sin(psi), ch - sign * R * np.cos(psi)])
    pts[0], pts[-1] = (x0, h0), (x1, h0)  # exact ends on the rail axis
    return pts


def _pipe_unit(
    design: str, L: float, H: float, radii: tuple[float, float, float], rng: np.random.Generator
) -> tuple[str, list[tuple[np.ndarray, float, str]]]:
    """One unit shape in unit coordinates: (pattern, [(polyline (n, 2) as (x, h), radius,
    role)]). Pipe ends sit on the axis of the pole / rail they meet, hidden inside it."""
    r_top, r_low, r_in = radii
    h_low = float(rng.uniform(0.15, 0.3))
    pipes: list[tuple[np.ndarray, float, str]] = [
        (np.array([[0.0, H], [L, H]]), r_top, "top_rail"),
        (np.array([[0.0, h_low], [L, h_low]]), r_low, "lower_rail"),
    ]
    if design == "simple":
        n = int(rng.integers(2, 5))
        for x in L * np.arange(1, n + 1) / (n + 1):
            pipes.append((np.array([[x, h_low], [x, H]]), r_in, "vertical"))
        return f"verticals-{n}", pipes
    if design == "diagonal":
        if rng.random() < 0.5:
            n = int(rng.integers(1, 3))
            edges = L * np.arange(n + 1) / n
            for x0, x1 in zip(edges[:-1], edges[1:], strict=True):
                pipes.append((np.array([[x0, h_low], [x1, H]]), r_in, "diagonal"))
                pipes.append((np.array([[x0, H], [x1, h_low]]), r_in, "diagonal"))
            return f"x-{n}", pipes
        n = int(rng.integers(2, 5))
        xs = L * np.arange(n + 1) / n
        hs = np.where(np.arange(n + 1) % 2 == 0, h_low, H)
        for k in range(n):
            pipes.append((np.array([[xs[k], hs[k]], [xs[k + 1], hs[k + 1]]]), r_in, "diagonal"))
        return f"zigzag-{n}", pipes
    if design == "curved":
        n = int(rng.integers(1, 4))
        edges = L * np.arange(n + 1) / n
        room = min(0.5 * L / n, H - h_low - 0.08)
        hanging = rng.random() < 0.5
        for x0, x1 in zip(edges[:-1], edges[1:], strict=True):
            sag = float(rng.uniform(0.4, 0.9)) * room
            arc = _arc(x0, x1, H, sag) if hanging else _arc(x0, x1, h_low, -sag)
            pipes.append((arc, r_in, "curved"))
        return f"{'hanging' if hanging else 'arch'}-{n}", pipes
    raise ValueError(f"unknown pipe guardrail design {design!r}; use one of {PIPE_DESIGNS}")


def pipe_guardrail(
    line: np.ndarray,
    rng: np.random.Generator,
    pole_spacing: float = 2.0,
    height: float | None = None,
    design: str | None = None,
    road_side: str = "left",
) -> Guardrail:
    """A pipe guardrail along `line`: vertical poles every `pole_spacing` m (see module doc),
    a top rail through the pole tops and one unit shape, drawn once with `rng` ("simple":
    lower rail + 2-4 verticals, "diagonal": lower rail + X or zig-zag pipes, "curved": lower
    rail + hanging arcs or arches), repeated in every unit. `height` = pole height (top rail
    axis), drawn in [0.8, 1.1] m when None."""
    bases, _ = pole_stations(line, pole_spacing)
    if len(bases) < 2:
        raise ValueError(f"line is shorter than one unit ({pole_spacing} m)")
    H = float(height) if height is not None else float(rng.uniform(0.8, 1.1))
    r_pole = float(rng.uniform(0.03, 0.04))
    r_top = float(rng.uniform(0.024, 0.03))
    r_low = min(float(rng.uniform(0.015, 0.025)), r_top)
    r_in = float(rng.uniform(0.012, r_low))
    design = str(design if design is not None else PIPE_DESIGNS[int(rng.integers(3))])
    pattern, unit = _pipe_unit(design, float(pole_spacing), H, (r_top, r_low, r_in), rng)

    ex, _ = _unit_frames(bases)
    meshes: list[Mesh] = []
    poles, pipes = [], []
    for i, base in enumerate(bases):
        top = base + H * _Z
        m = cylinder(base, top, r_pole, segments=16)
        m.part[:] = Part.POLE
        meshes.append(m)
        poles.append(
            {
                "base": base.tolist(),
                "top": top.tolist(),
                "radius": r_pole,
                "shape": "round",
                "index": i,
            }
        )
    for i in range(len(bases) - 1):
        for xh, r, role in unit:
            world = bases[i] + xh[:, :1] * ex[i] + xh[:, 1:] * _Z
            m = tube(world, r, segments=12)
            m.part[:] = Part.PIPE
            meshes.append(m)
            pipes.append({"polyline": world.tolist(), "radius": r, "role": role, "unit": i})
    model = {
        "kind": "pipe",
        "design": design,
        "pattern": pattern,
        "road_side": road_side,
        "height": H,
        "poles": poles,
        "pipes": pipes,
        "beam": None,
        "spacers": [],
        "unit_length": float(pole_spacing),
        "unit_count": len(bases) - 1,
    }
    return Guardrail(Mesh.merge(meshes), model)


# ----------------------------------------------------------------------------- beam guardrails


def w_beam_section(samples: int = 25) -> np.ndarray:
    """AASHTO M180-style W-beam section (samples, 2) as (u, v): v from -depth/2 to +depth/2,
    u >= 0 bulging towards the road with two peaks (v = +-depth/4) of the corrugation depth;
    u = 0 at the back contact lines (edges and middle valley)."""
    v = np.linspace(-0.5 * W_BEAM_DEPTH, 0.5 * W_BEAM_DEPTH, samples)
    u = 0.5 * W_BEAM_CORRUGATION * (1.0 - np.cos(4.0 * np.pi * (v / W_BEAM_DEPTH + 0.5)))
    return np.column_stack([u, v])


def beam_guardrail(
    line: np.ndarray,
    rng: np.random.Generator,
    post_spacing: float = 2.0,
    road_side: str = "left",
    post_shape: str | None = None,
    blockout: bool | None = None,
) -> Guardrail:
    """A W-beam guardrail along `line`: posts (round r 0.05-0.07 or 0.10 x 0.15 m box, 0.75-0.8
    m high) every `post_spacing` m, the W-beam (centre 0.55 m up to its top at the post top)
    swept along the line on the road side, its back `offset` from the post axis: post
    half-depth + block-out spacer (0.05-0.12 m, so ~0.1-0.2 m) or bolted to the post face
    without one. Spacers are labelled POLE (post assembly)."""
    if road_side not in ("left", "right"):
        raise ValueError("road_side must be 'left' or 'right'")
    L = _clean_line(line)
    bases, st = pole_stations(L, post_spacing)
    if len(bases) < 2:
        raise ValueError(f"line is shorter than one unit ({post_spacing} m)")
    side = 1.0 if road_side == "left" else -1.0
    post_h = float(rng.uniform(0.75, 0.8))
    centre = float(rng.uniform(0.55, post_h - 0.5 * W_BEAM_DEPTH))
    shape = str(post_shape if post_shape is not None else ("round", "box")[int(rng.integers(2))])
    r_post = float(rng.uniform(0.05, 0.07))
    box_size = (0.10, 0.15)  # along the line, across
    half = r_post if shape == "round" else 0.5 * box_size[1]
    has_block = bool(rng.random() < 0.6) if blockout is None else bool(blockout)
    gap = float(rng.uniform(0.05, 0.12)) if has_block else 0.002
    offset = half + gap

    # beam path: the line between the end posts, resampled through every post
    S = _stations(L)
    n_sub = max(1, int(np.ceil(post_spacing / _BEAM_STEP)))
    frac = np.arange(n_sub) / n_sub
    s = np.r_[(st[:-1, None] + np.diff(st)[:, None] * frac[None, :]).ravel(), st[-1]]
    ground = _at(L, S, s)
    horiz = np.gradient(ground, axis=0) * np.array([1.0, 1.0, 0.0])
    left = _unit(np.cross(_Z, _unit(horiz)))
    path = ground + side * offset * left + centre * _Z
    section = w_beam_section()
    section[:, 0] *= side  # u is "left of the path": mirror for a road on the right
    beam = sweep_profile(section, path)
    beam.part[:] = Part.BEAM

    meshes, posts, spacers = [beam], [], []
    post_left = left[::n_sub]
    yaws = np.arctan2(-post_left[:, 0], post_left[:, 1])  # heading of the line at each post
    for i, (b, yaw, lv) in enumerate(zip(bases, yaws, post_left, strict=True)):
        top = b + post_h * _Z
        entry = {"base": b.tolist(), "top": top.tolist(), "shape": shape, "index": i}
        if shape == "round":
            m = cylinder(b, top, r_post, segments=16)
            entry["radius"] = r_post
        else:
            m = box((box_size[0], box_size[1], post_h), b + 0.5 * post_h * _Z, float(yaw))
            entry.update(
                radius=float(np.sqrt(box_size[0] * box_size[1] / np.pi)),
                size=list(box_size),
                yaw=float(yaw),
            )
        m.part[:] = Part.POLE
        meshes.append(m)
        posts.append(entry)
        if has_block:
            inner = 0.5 * half
            size = (0.15, offset - inner, 0.3)
            c = b + side * 0.5 * (inner + offset) * lv + centre * _Z
            m = box(size, c, float(yaw))
            m.part[:] = Part.POLE
            meshes.append(m)
            spacers.append({"center": c.tolist(), "size": list(size), "yaw": float(yaw)})
    model = {
        "kind": "beam",
        "design": "w-beam",
        "post_shape": shape,
        "blockout": has_block,
        "road_side": road_side,
        "height": post_h,
        "poles": posts,
        "pipes": [],
        "beam": {
            "section": section.tolist(),
            "path": path.tolist(),
            "up": [0.0, 0.0, 1.0],
            "centre_height": centre,
            "offset": offset,
        },
        "spacers": spacers,
        "unit_length": float(post_spacing),
        "unit_count": len(bases) - 1,
    }
    return Guardrail(Mesh.merge(meshes), model)


# ----------------------------------------------------------------------------- distances


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
        d = _unit(np.diff(P, axis=0))
        t = np.concatenate([d[:1], _unit(d[:-1] + d[1:]), d[-1:]])
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
    D = _unit(B - A)[seg]
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
    d = _unit(np.diff(P, axis=0))
    left = _unit(np.cross(up, d))
    t = np.concatenate([d[:1], _unit(d[:-1] + d[1:]), d[-1:]])
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
    out = np.full(len(pts), np.inf)
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
        centres = pieces["a"] + 0.5 * pieces["L"][:, None] * pieces["d"]
        out = np.minimum(
            out,
            _nearest(
                pts,
                centres,
                lambda p, i: _piece_dist(pieces, p, i),
                lambda D: (D - half) / slope - pieces["r"].max(),
                cutoff,
            ),
        )
    boxes = _boxes(model)
    if boxes is not None:
        reach = float(np.linalg.norm(boxes["h"], axis=1).max())
        out = np.minimum(
            out,
            _nearest(
                pts,
                boxes["c"],
                lambda p, i: _box_dist(boxes, p, i),
                lambda D: D - reach,
                cutoff,
                k0=4,
            ),
        )
    if model.get("beam"):
        bm = _beam_segments(model["beam"])
        sec_c = bm["sec"].mean(0)
        centres = (
            bm["a"] + 0.5 * bm["L"][:, None] * bm["d"] + sec_c[0] * bm["left"] + sec_c[1] * bm["up"]
        )
        reach = float(0.5 * bm["L"].max() + 2.0 * np.linalg.norm(bm["sec"] - sec_c, axis=1).max())
        out = np.minimum(
            out,
            _nearest(
                pts,
                centres,
                lambda p, i: _beam_dist(bm, p, i),
                lambda D: D - reach,
                cutoff,
                k0=8,
                chunk_pairs=1 << 16,
            ),
        )
    return out
