"""Mesh primitives: closed, outward-wound solids with the right size; sweeps on their curves."""

from __future__ import annotations

import numpy as np
import pytest

from app.simulate.meshes import (
    box,
    cylinder,
    ellipsoid,
    extrude_polygon,
    strip,
    sweep_profile,
    tube,
)
from app.simulate.scene import Mesh


def edge_counts(m: Mesh) -> np.ndarray:
    T = m.triangles
    e = np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def face_normals(m: Mesh) -> np.ndarray:
    V, T = m.vertices, m.triangles
    return np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])


def volume(m: Mesh) -> float:
    V, T = m.vertices, m.triangles
    return float(np.einsum("ij,ij->i", V[T[:, 0]], np.cross(V[T[:, 1]], V[T[:, 2]])).sum() / 6)


def outward(m: Mesh) -> float:
    V, T = m.vertices, m.triangles
    n = face_normals(m)
    return float(np.mean(np.einsum("ij,ij->i", n, V[T].mean(1) - V.mean(0))))


def arc(radius: float, angle: float, n: int) -> np.ndarray:
    a = np.linspace(0.0, angle, n)
    return np.column_stack([radius * np.cos(a), radius * np.sin(a), 0.2 * a])


def polyline_distance(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    a, b = line[:-1], line[1:]
    e = b - a
    t = np.einsum("nsk,sk->ns", points[:, None] - a[None], e) / np.einsum("sk,sk->s", e, e)
    foot = a[None] + np.clip(t, 0, 1)[..., None] * e[None]
    return np.linalg.norm(points[:, None] - foot, axis=2).min(1)


SOLIDS = {
    "box": lambda: box((1.0, 2.0, 3.0), (1.0, -2.0, 0.5), yaw=0.7),
    "cylinder": lambda: cylinder((0, 0, 0), (1.0, 2.0, 2.0), 0.4, segments=16),
    "tube": lambda: tube(arc(2.0, 2.5, 30), 0.05, segments=12),
    "extrude": lambda: extrude_polygon(
        np.array([[0, 0], [6, 0], [6, 4], [4, 4], [4, 3], [2, 3], [2, 4], [0, 4]]), -0.2, 9.0
    ),
    "ellipsoid": lambda: ellipsoid((1, 2, 3), (2.0, 1.0, 0.5), subdivisions=2),
}


@pytest.mark.parametrize("name", sorted(SOLIDS))
def test_solids_are_closed_and_wound_outwards(name: str) -> None:
    m = SOLIDS[name]()
    assert np.all(edge_counts(m) == 2)
    assert outward(m) > 0
    assert volume(m) > 0
    assert m.part.shape == (len(m.triangles),) and not m.part.any()


def test_box_has_12_triangles_and_exact_volume() -> None:
    m = box((1.0, 2.0, 3.0), (5.0, 5.0, 5.0), yaw=0.3)
    assert len(m.triangles) == 12
    assert volume(m) == pytest.approx(6.0, rel=1e-12)
    np.testing.assert_allclose(m.vertices.mean(0), [5.0, 5.0, 5.0])
    assert np.ptp(m.vertices[:, 2]) == pytest.approx(3.0)


def test_cylinder_volume_counts_and_radius() -> None:
    S, r, p0, p1 = 64, 0.3, np.array([0.0, 0, 0]), np.array([0.0, 3.0, 4.0])
    m = cylinder(p0, p1, r, segments=S)
    assert len(m.triangles) == 4 * S
    h = 5.0
    polygon_area = 0.5 * S * r * r * np.sin(2 * np.pi / S)
    assert volume(m) == pytest.approx(polygon_area * h, rel=1e-9)
    assert volume(m) == pytest.approx(np.pi * r * r * h, rel=0.01)
    rim = polyline_distance(m.vertices[:-2], np.stack([p0, p1]))
    np.testing.assert_allclose(rim, r, atol=1e-12)
    assert len(cylinder(p0, p1, r, segments=S, caps=False).triangles) == 2 * S


def test_tube_follows_a_curved_polyline_without_twist() -> None:
    line = arc(3.0, np.pi, 40)
    r, S = 0.04, 12
    m = tube(line, r, segments=S)
    assert len(m.triangles) == 2 * S * (len(line) - 1) + 2 * S
    rings = m.vertices[:-2]
    d = polyline_distance(rings, line)
    # mitred joints: on both neighbouring swept circles; only the outer side of a bend sits
    # r / cos(half turn) from the joint itself
    seg = np.diff(line, axis=0)
    seg /= np.linalg.norm(seg, axis=1, keepdims=True)
    half_turn = 0.5 * np.arccos(np.einsum("ij,ij->i", seg[:-1], seg[1:]).min())
    assert np.abs(d - r).max() <= r * (1 / np.cos(half_turn) - 1) + 1e-12
    assert np.median(np.abs(d - r)) < 1e-12
    # rotation-minimising: consecutive rings' first vertices stay on the same side
    first = rings.reshape(len(line), S, 3)[:, 0] - line
    cos = np.einsum("ij,ij->i", first[:-1], first[1:]) / r**2
    assert cos.min() > np.cos(np.radians(10))


def test_sweep_profile_vertices_lie_on_the_profile_and_double_sided() -> None:
    prof = np.array([[0.0, -0.1], [0.05, 0.0], [0.0, 0.1], [0.05, 0.2]])
    path = np.column_stack([np.linspace(0, 10, 6), np.full(6, 2.0), np.full(6, 0.5)])
    m = sweep_profile(prof, path)
    V = m.vertices.reshape(len(path), len(prof), 3)
    # path along +x, left = +y, up = +z
    np.testing.assert_allclose(V[..., 1] - 2.0, np.broadcast_to(prof[:, 0], V.shape[:2]))
    np.testing.assert_allclose(V[..., 2] - 0.5, np.broadcast_to(prof[:, 1], V.shape[:2]))
    np.testing.assert_allclose(V[..., 0], np.broadcast_to(path[:, :1], V.shape[:2]))
    T = m.triangles
    half = len(T) // 2
    assert len(T) == 2 * 2 * (len(path) - 1) * (len(prof) - 1)
    np.testing.assert_array_equal(T[half:], T[:half, ::-1])  # both windings
    n = face_normals(m)
    np.testing.assert_allclose(n[:half], -n[half:])


def test_sweep_profile_on_a_curve_keeps_the_section() -> None:
    prof = np.array([[0.0, 0.0], [0.2, 0.1], [0.0, 0.3]])
    path = arc(20.0, 0.5, 20) * [1, 1, 0] + [0, 0, 1.0]
    m = sweep_profile(prof, path)
    V = m.vertices.reshape(len(path), len(prof), 3)
    rad = np.linalg.norm(V[..., :2], axis=-1)
    # left of a counter-clockwise arc is inwards: u reduces the radius (mitre: / cos)
    half_angle = 0.5 * 0.5 / 19
    inner = 20.0 - rad[1:-1]
    expect = np.broadcast_to(prof[:, 0], inner.shape)
    np.testing.assert_allclose(inner * np.cos(half_angle), expect, atol=1e-9)
    np.testing.assert_allclose(V[..., 2] - 1.0, np.broadcast_to(prof[:, 1], V.shape[:2]))


def test_sweep_profile_with_thickness_offsets_two_sheets() -> None:
    prof = np.array([[0.0, 0.0], [0.0, 0.3]])
    path = np.array([[0.0, 0, 0], [5.0, 0, 0]])
    m = sweep_profile(prof, path, thickness=0.004)
    ys = np.unique(np.round(m.vertices[:, 1], 9))
    np.testing.assert_allclose(ys, [-0.002, 0.002])
    n = face_normals(m)
    side = np.sign(m.vertices[m.triangles[:, 0], 1])
    assert np.all(np.sign(n[:, 1]) == side)  # each sheet faces away from the other


def test_strip_faces_up_whichever_side_is_given_first() -> None:
    x = np.linspace(0, 10, 11)
    left = np.column_stack([x, np.full(11, 1.0), 0.01 * x])
    right = np.column_stack([x, np.full(11, -1.0), 0.01 * x])
    for a, b in ((left, right), (right, left)):
        m = strip(a, b)
        assert len(m.triangles) == 2 * 10
        assert np.all(face_normals(m)[:, 2] > 0)
        assert np.abs(face_normals(m)).sum(1).min() > 0  # no degenerate triangles


def test_extrude_polygon_with_a_recess() -> None:
    poly = np.array([[0, 0], [4, 0], [4, 3], [3, 3], [3, 1], [1, 1], [1, 3], [0, 3]], float)
    m = extrude_polygon(poly, 0.0, 2.0)
    assert len(m.triangles) == 2 * 8 + 2 * 6
    assert volume(m) == pytest.approx((12.0 - 4.0) * 2.0)
    roof = face_normals(m)[:, 2] > 0
    assert roof.sum() == 6 and np.allclose(m.vertices[m.triangles[roof]][..., 2], 2.0)
    assert volume(extrude_polygon(poly[::-1], 0.0, 2.0)) == pytest.approx(16.0)  # clockwise ok


def test_ellipsoid_vertices_on_surface_and_counts() -> None:
    c, r = np.array([1.0, 2.0, 3.0]), np.array([2.0, 1.0, 0.5])
    for k in (0, 1, 2, 3):
        m = ellipsoid(c, r, subdivisions=k)
        assert len(m.triangles) == 20 * 4**k
        np.testing.assert_allclose((((m.vertices - c) / r) ** 2).sum(1), 1.0)
    m = ellipsoid(c, r, 2)
    assert m.vertices[:, 2].max() == pytest.approx(3.5)
    assert m.vertices[:, 2].min() == pytest.approx(2.5)
    assert volume(m) == pytest.approx(4 / 3 * np.pi * r.prod(), rel=0.05)
