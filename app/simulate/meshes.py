"""Triangle-mesh primitives the street scenes are built from.

Every solid (box, cylinder, tube, extruded polygon, ellipsoid) comes back closed (each edge is
shared by exactly two triangles) and wound counter-clockwise seen from outside, so face normals
point out; sheets (`sweep_profile`) carry both windings and surfaces (`strip`) face up. All
functions return a `Mesh` with `part` 0; callers set parts (guardrails) themselves.

Tubes and swept profiles are mitred at polyline joints: the cross-section at a joint is the
intersection of both neighbouring straight sweeps with the bisector plane, so every vertex lies
exactly on the sweep of the segment before and after it (`guardrail_distance.surface_distance`
relies on that). Tube frames are transported without twist (rotation-minimising).
"""

from __future__ import annotations

import numpy as np

from app.geometry.mesh_grid import cap_faces, grid_faces
from app.simulate.scene import Mesh

_Z = np.array([0.0, 0.0, 1.0])


def unit_rows(v: np.ndarray) -> np.ndarray:
    """Rows of `v` scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0.0, n, 1.0)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _dedupe(polyline: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Polyline without consecutive repeated points (they have no direction)."""
    P = np.asarray(polyline, dtype=np.float64).reshape(-1, 3)
    keep = np.r_[True, np.linalg.norm(np.diff(P, axis=0), axis=1) > eps]
    return P[keep]


def box(
    size: np.ndarray | tuple[float, float, float],
    center: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    yaw: float = 0.0,
) -> Mesh:
    """Box of `size` (x, y, z) turned by `yaw` about z around `center`: 12 triangles."""
    half = 0.5 * np.asarray(size, dtype=np.float64)
    signs = np.array(
        [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64,
    )  # fmt: skip
    tris = np.array(
        [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
         [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7], [1, 2, 6], [1, 6, 5]],
    )  # fmt: skip
    V = (signs * half) @ _rot_z(yaw).T + np.asarray(center, dtype=np.float64)
    return Mesh(V, tris)


def _transport_normals(d: np.ndarray) -> np.ndarray:
    """One normal per segment direction `d` (M, 3), each the previous one carried over by the
    smallest rotation between the directions (parallel transport: the frame does not twist).
    Sequential by nature; a loop over the polyline's segments, not over surface vertices."""
    n = np.empty_like(d)
    helper = _Z if abs(d[0] @ _Z) < 0.9 else np.array([1.0, 0.0, 0.0])
    n[0] = unit_rows(np.cross(d[0], helper))
    for j in range(1, len(d)):
        a, b, x = d[j - 1], d[j], n[j - 1]
        v, c = np.cross(a, b), float(a @ b)
        if c > -1.0 + 1e-9:
            x = x * c + np.cross(v, x) + v * (v @ x) / (1.0 + c)
        x = x - (x @ b) * b  # keep it exactly perpendicular to the new direction
        n[j] = unit_rows(x)
    return n


def _mitre(P: np.ndarray, d: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Cross-section offsets `q` (K, S, 3), given in the plane normal to the segment before each
    vertex, slid along that segment onto the bisector plane of the joint: vertices (K, S, 3)."""
    K = len(P)
    t = np.empty((K, 3))
    t[0], t[-1] = d[0], d[-1]
    if K > 2:
        t[1:-1] = unit_rows(d[:-1] + d[1:])
    dj = d[np.r_[0, np.arange(K - 1)]]
    qt = np.einsum("ksc,kc->ks", q, t)
    q = q - (qt / np.einsum("kc,kc->k", dj, t)[:, None])[..., None] * dj[:, None, :]
    return P[:, None, :] + q


def tube(polyline: np.ndarray, radius: float, segments: int = 12, caps: bool = True) -> Mesh:
    """A circle of `radius` swept along `polyline` (K, 3): pipes, bent pipes, limbs.

    Rings are mitred at the joints (see module doc); with `caps` both ends are closed by flat
    discs (a fan around a centre vertex), giving a closed mesh.
    """
    P = _dedupe(polyline)
    if len(P) < 2:
        raise ValueError("tube needs a polyline of at least two distinct points")
    d = unit_rows(np.diff(P, axis=0))
    n = _transport_normals(d)
    b = np.cross(d, n)
    j = np.r_[0, np.arange(len(P) - 1)]
    theta = 2.0 * np.pi * np.arange(segments) / segments
    q = radius * (
        np.cos(theta)[None, :, None] * n[j][:, None, :]
        + np.sin(theta)[None, :, None] * b[j][:, None, :]
    )
    K, S = len(P), segments
    V = _mitre(P, d, q).reshape(-1, 3)
    T = grid_faces(K, S, wrap=True)
    if caps:
        V = np.concatenate([V, P[:1], P[-1:]])
        T = np.concatenate([T, cap_faces(K, S)])
    return Mesh(V, T)


def cylinder(
    p0: np.ndarray | tuple[float, float, float],
    p1: np.ndarray | tuple[float, float, float],
    radius: float,
    segments: int = 16,
    caps: bool = True,
) -> Mesh:
    """Straight cylinder from `p0` to `p1` (any axis); 4 * segments triangles with caps."""
    return tube(np.stack([np.asarray(p0, float), np.asarray(p1, float)]), radius, segments, caps)


def sweep_profile(
    profile: np.ndarray,
    path: np.ndarray,
    up: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0),
    thickness: float = 0.0,
) -> Mesh:
    """An open 2D curve swept along `path` (K, 3) as a thin sheet (W-beam guardrails).

    `profile` (P, 2) holds (u, v): u = offset perpendicular to the path and to `up` (horizontal
    for the default `up`), positive to the LEFT of the path direction; v = height offset along
    `up` made perpendicular to the path segment. The sheet is double-sided: with
    `thickness` 0 every quad appears with both windings on the same vertices (the ray caster
    turns normals towards the ray); with `thickness` > 0 the two sides are separate sheets
    offset by +-thickness/2 along the profile normal, each wound outwards.
    """
    prof = np.asarray(profile, dtype=np.float64).reshape(-1, 2)
    P = _dedupe(path)
    if len(P) < 2 or len(prof) < 2:
        raise ValueError("sweep_profile needs at least two profile and two path points")
    d = unit_rows(np.diff(P, axis=0))
    left = unit_rows(np.cross(np.asarray(up, dtype=np.float64), d))
    upv = np.cross(d, left)
    j = np.r_[0, np.arange(len(P) - 1)]

    def place(pr: np.ndarray) -> np.ndarray:
        q = pr[None, :, 0, None] * left[j][:, None, :] + pr[None, :, 1, None] * upv[j][:, None, :]
        return _mitre(P, d, q).reshape(-1, 3)

    K, S = len(P), len(prof)
    T = grid_faces(K, S, wrap=False)  # wound so its normal is the profile tangent turned clockwise
    if thickness <= 0.0:
        return Mesh(place(prof), np.concatenate([T, T[:, ::-1]]))
    tangent = unit_rows(np.gradient(prof, axis=0))
    n2 = np.stack([tangent[:, 1], -tangent[:, 0]], -1)
    h = 0.5 * thickness
    V = np.concatenate([place(prof + h * n2), place(prof - h * n2)])
    return Mesh(V, np.concatenate([T, T[:, ::-1] + K * S]))


def strip(left: np.ndarray, right: np.ndarray) -> Mesh:
    """Surface between two polylines (K, 3) of equal length (road, sidewalk, lane markings),
    two triangles per quad, wound so the normals point up (+z) whichever side is which."""
    L = np.asarray(left, dtype=np.float64).reshape(-1, 3)
    R = np.asarray(right, dtype=np.float64).reshape(-1, 3)
    if len(L) != len(R) or len(L) < 2:
        raise ValueError("strip needs two polylines of the same length (>= 2 points)")
    K = len(L)
    k = np.arange(K - 1)
    lk, lk1, rk, rk1 = k, k + 1, K + k, K + k + 1
    T = np.concatenate([np.stack([rk, rk1, lk1], -1), np.stack([rk, lk1, lk], -1)])
    V = np.concatenate([L, R])
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    if n[:, 2].sum() < 0.0:
        T = T[:, ::-1]
    return Mesh(V, T)


def _ear_clip(poly: np.ndarray) -> np.ndarray:
    """Triangles (P - 2, 3) of a simple counter-clockwise polygon (P, 2) by ear clipping.
    Polygons here are small (building footprints), so the O(P^2) loop is fine."""
    idx = list(range(len(poly)))
    tris: list[tuple[int, int, int]] = []
    while len(idx) > 3:
        n = len(idx)
        pts = poly[idx]
        prev, nxt = np.roll(pts, 1, axis=0), np.roll(pts, -1, axis=0)
        e1, e2 = pts - prev, nxt - pts
        cross = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        scale = max(float(np.ptp(poly, axis=0).max()) ** 2, 1e-300)
        clip = None
        for i in np.flatnonzero(cross > 1e-12 * scale):
            a, b, c = prev[i], pts[i], nxt[i]
            others = np.delete(pts, [(i - 1) % n, i, (i + 1) % n], axis=0)
            if len(others) and _in_triangle(others, a, b, c).any():
                continue
            clip = int(i)
            break
        if clip is None:  # only degenerate (collinear) corners left: clip the flattest one
            clip = int(np.argmin(np.abs(cross)))
        tris.append((idx[(clip - 1) % n], idx[clip], idx[(clip + 1) % n]))
        idx.pop(clip)
    tris.append((idx[0], idx[1], idx[2]))
    return np.array(tris, dtype=np.int64)


def _in_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Which points (N, 2) lie inside or on the counter-clockwise triangle abc."""

    def side(o: np.ndarray, e: np.ndarray) -> np.ndarray:
        return (e[0] - o[0]) * (p[:, 1] - o[1]) - (e[1] - o[1]) * (p[:, 0] - o[0])

    eps = -1e-12 * max(float(np.abs(np.stack([a, b, c])).max()) ** 2, 1.0)
    same = (
        np.all(np.isclose(p, a), axis=1)
        | np.all(np.isclose(p, b), axis=1)
        | np.all(np.isclose(p, c), axis=1)
    )
    return (side(a, b) >= eps) & (side(b, c) >= eps) & (side(c, a) >= eps) & ~same


def extrude_polygon(polygon: np.ndarray, z0: float, z1: float, bottom: bool = True) -> Mesh:
    """Prism over a simple polygon (P, 2) from `z0` to `z1`: vertical walls, a flat roof and
    (with `bottom`) a floor, closed. A clockwise polygon is reversed first."""
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    x, y = poly[:, 0], poly[:, 1]
    if np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) < 0.0:
        poly = poly[::-1]
    P = len(poly)
    V = np.concatenate(
        [np.column_stack([poly, np.full(P, z0)]), np.column_stack([poly, np.full(P, z1)])]
    )
    i = np.arange(P)
    i1 = (i + 1) % P
    walls = np.concatenate([np.stack([i, i1, P + i1], -1), np.stack([i, P + i1, P + i], -1)])
    roof = _ear_clip(poly)
    parts = [walls, roof + P]
    if bottom:
        parts.append(roof[:, ::-1])
    return Mesh(V, np.concatenate(parts))


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """Unit icosahedron with vertices at both poles (so scaled spheres reach their full height)."""
    k = np.arange(5)
    a = 2.0 * np.pi * k / 5.0
    z, r = 1.0 / np.sqrt(5.0), 2.0 / np.sqrt(5.0)
    upper = np.column_stack([r * np.cos(a), r * np.sin(a), np.full(5, z)])
    lower = np.column_stack([r * np.cos(a + np.pi / 5), r * np.sin(a + np.pi / 5), np.full(5, -z)])
    V = np.concatenate([[[0.0, 0.0, 1.0]], upper, lower, [[0.0, 0.0, -1.0]]])
    u, u1, lo, lo1 = 1 + k, 1 + (k + 1) % 5, 6 + k, 6 + (k + 1) % 5
    F = np.concatenate(
        [
            np.stack([np.zeros(5, int), u, u1], -1),
            np.stack([u, lo, u1], -1),
            np.stack([u1, lo, lo1], -1),
            np.stack([np.full(5, 11), lo1, lo], -1),
        ]
    )
    return V, F


def _orient_outwards(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Faces of a star-shaped closed mesh around the origin, re-wound so normals point out."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = np.einsum("ij,ij->i", n, V[F].mean(1)) < 0.0
    F = F.copy()
    F[flip] = F[flip][:, ::-1]
    return F


def ellipsoid(
    center: np.ndarray | tuple[float, float, float],
    radii: np.ndarray | tuple[float, float, float],
    subdivisions: int = 2,
) -> Mesh:
    """Subdivided icosahedron scaled to `radii` (tree crowns, heads): 20 * 4**subdivisions
    triangles, vertices exactly on the ellipsoid, one at the top and one at the bottom."""
    V, F = _icosahedron()
    F = _orient_outwards(V, F)
    for _ in range(subdivisions):
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(e, axis=0, return_inverse=True)
        mids = unit_rows(V[uniq[:, 0]] + V[uniq[:, 1]])
        m01, m12, m20 = (inv.reshape(3, -1) + len(V))[:]
        a, b, c = F[:, 0], F[:, 1], F[:, 2]
        F = np.concatenate(
            [
                np.stack([a, m01, m20], -1),
                np.stack([b, m12, m01], -1),
                np.stack([c, m20, m12], -1),
                np.stack([m01, m12, m20], -1),
            ]
        )
        V = np.concatenate([V, mids])
    return Mesh(V * np.asarray(radii, dtype=np.float64) + np.asarray(center, dtype=np.float64), F)


def foliage(
    radii: np.ndarray | tuple[float, float, float],
    rng: np.random.Generator,
    roundness: float = 2.0,
    leaf: float = 0.08,
    leaves_per_m3: float = 1200.0,
) -> Mesh:
    """Leaves: small triangles of random orientation filling a lumpy volume about the origin,
    so a laser ray goes some way in before one stops it (a bush's scattered returns, not a
    smooth shell). The volume is |x/a|^p + |y/b|^p + |z/c|^p <= 1 with p = `roundness` (2 an
    ellipsoid, 4 a trimmed hedge), its boundary pushed in and out by a few random waves; leaves
    are drawn `leaves_per_m3` per cubic metre of its bounding box and kept inside it."""
    radii = np.asarray(radii, dtype=np.float64)
    box_volume = 8.0 * float(np.prod(radii))
    drawn = rng.uniform(-1.0, 1.0, (int(leaves_per_m3 * box_volume) + 1, 3))
    waves = rng.normal(size=(4, 3))
    phase = rng.uniform(0.0, 2.0 * np.pi, 4)
    lump = 1.0 + 0.08 * np.cos(drawn @ waves.T * np.pi + phase).sum(axis=1)
    inside = (np.abs(drawn) ** roundness).sum(axis=1) <= lump**roundness
    centres = drawn[inside] * radii
    n = len(centres)
    a = unit_rows(rng.normal(size=(n, 3)))
    b = unit_rows(np.cross(a, rng.normal(size=(n, 3))))
    vertices = np.stack([centres, centres + leaf * a, centres + leaf * b], axis=1)
    return Mesh(vertices.reshape(-1, 3), np.arange(3 * n, dtype=np.int32).reshape(n, 3))
