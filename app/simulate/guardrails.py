"""The guardrail paper's two guardrail kinds, built along a ground line, with their exact models.

Matsumoto, Mori & Masuda build guardrails from identical *unit shapes* between poles: pipe
guardrails (a top rail plus a repeated pattern of thin pipes, often a municipal design) and beam
guardrails (a W-beam section swept along the rail, on posts). The simulator needs both as a
triangle mesh (for ray casting, each triangle labelled PIPE / BEAM / POLE) and as a JSON-ready
parametric model (the ground truth the reconstruction is scored against and that
`guardrail_distance.surface_distance` measures points against).

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

from dataclasses import dataclass

import numpy as np

from app.core.labels import Part
from app.simulate.meshes import box, cylinder, sweep_profile, tube, unit_rows
from app.simulate.scene import Mesh

W_BEAM_DEPTH = 0.311  # m, AASHTO M180 W-beam: height of the section
W_BEAM_CORRUGATION = 0.083  # m, depth of its two corrugations
_Z = np.array([0.0, 0.0, 1.0])
_ARC_STEP = np.radians(6.0)  # bent pipes: at most 6 degrees per polyline segment
_BEAM_STEP = 0.5  # m, longest beam path segment (follows curves)


@dataclass
class Guardrail:
    """A guardrail: world-coordinate mesh (part per triangle) and its JSON-ready model."""

    mesh: Mesh
    model: dict


# ----------------------------------------------------------------------------- ground line


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
    ex = unit_rows(np.diff(bases, axis=0))
    ey = unit_rows(np.cross(_Z, ex))
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
    left = unit_rows(np.cross(_Z, unit_rows(horiz)))
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
