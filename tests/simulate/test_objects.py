"""Street objects: sizes in their ranges, standing on z = 0, deterministic per seed."""

from __future__ import annotations

import numpy as np
import pytest

from app.simulate import objects
from app.simulate.scene import Mesh

SEEDS = range(8)
EPS = 1e-6

# kind -> (length, width, height) ranges from the brief / real vehicles
RANGES = {
    "car": ((4.0, 4.8), (1.7, 1.9), (1.4, 1.6)),
    "van": ((4.8, 5.5), (1.9, 2.1), (1.9, 2.4)),
    "truck": ((7.0, 10.0), (2.4, 2.5), (3.0, 3.6)),
    "bus": ((10.5, 13.0), (2.5, 2.55), (3.0, 3.3)),
    "tram": ((20.0, 30.0), (2.4, 2.65), (3.3, 3.6)),
    "caravan": ((5.0, 7.5), (2.2, 2.5), (2.4, 2.7)),
}


def inside(v: float, lo: float, hi: float, tol: float = EPS) -> bool:
    return lo - tol <= v <= hi + tol


def bbox(m: Mesh) -> tuple[np.ndarray, np.ndarray]:
    return m.vertices.min(0), m.vertices.max(0)


@pytest.mark.parametrize("kind", sorted(RANGES))
def test_vehicle_sizes_in_range_centred_and_grounded(kind: str) -> None:
    for seed in SEEDS:
        o = getattr(objects, kind)(np.random.default_rng(seed))
        lo, hi = bbox(o.mesh)
        for v, (a, b) in zip(o.size, RANGES[kind], strict=True):
            assert inside(v, a, b), (kind, seed, o.size)
        assert lo[2] == pytest.approx(0.0, abs=1e-12)
        np.testing.assert_allclose(lo[:2], -hi[:2], atol=1e-9)  # footprint centred on origin
        np.testing.assert_allclose(hi - lo, o.size)
        assert o.size[0] == pytest.approx(o.params["length"])


@pytest.mark.parametrize(
    "make",
    [
        objects.car,
        objects.van,
        objects.truck,
        objects.bus,
        objects.tram,
        objects.caravan,
        objects.pedestrian,
        objects.cyclist,
        objects.tree,
        objects.pole,
        objects.sign,
    ],
)
def test_same_seed_same_object_and_seeds_differ(make) -> None:
    a, b, c = (
        make(np.random.default_rng(7)),
        make(np.random.default_rng(7)),
        make(np.random.default_rng(8)),
    )
    assert a.meshes.keys() == b.meshes.keys()
    for k in a.meshes:
        np.testing.assert_array_equal(a.meshes[k].vertices, b.meshes[k].vertices)
        np.testing.assert_array_equal(a.meshes[k].triangles, b.meshes[k].triangles)
    assert a.size == b.size and a.size != c.size
    assert min(a.mesh.vertices[:, 2]) == pytest.approx(0.0, abs=1e-12)


def test_pedestrian_height_and_width() -> None:
    for seed in SEEDS:
        o = objects.pedestrian(np.random.default_rng(seed))
        assert inside(o.size[2], 1.55, 1.95)
        assert o.size[2] == pytest.approx(o.params["height"], abs=1e-9)
        assert 0.4 <= o.size[1] <= 0.6


def test_cyclist_has_bicycle_and_rider() -> None:
    for seed in SEEDS:
        o = objects.cyclist(np.random.default_rng(seed))
        assert set(o.meshes) == {"bicycle", "rider"}
        blo, bhi = bbox(o.meshes["bicycle"])
        rlo, rhi = bbox(o.meshes["rider"])
        assert 1.6 <= bhi[0] - blo[0] <= 1.9  # ~1.75 m long bicycle
        assert blo[2] == pytest.approx(0.0, abs=1e-12)  # wheels on the ground
        assert rhi[2] > bhi[2] + 0.5  # rider sits on top
        assert 1.5 <= o.size[2] <= 2.0


def test_tree_trunk_and_crown() -> None:
    for seed in SEEDS:
        o = objects.tree(np.random.default_rng(seed))
        p = o.params
        assert inside(p["trunk_radius"], 0.1, 0.25) and inside(p["trunk_height"], 2.0, 3.5)
        assert inside(p["crown_radius"], 1.5, 3.0)
        tlo, thi = bbox(o.meshes["trunk"])
        clo, chi = bbox(o.meshes["crown"])
        assert thi[2] == pytest.approx(p["trunk_height"])
        assert thi[0] - tlo[0] == pytest.approx(2 * p["trunk_radius"], rel=0.05)
        assert clo[2] > 0.5 * p["trunk_height"] and chi[2] > thi[2] + 1.0  # crown above
        assert (chi[0] - clo[0]) == pytest.approx(2 * p["crown_radius"], rel=0.05)


def test_pole_heights_and_arm_towards_minus_y() -> None:
    lamp = objects.pole(np.random.default_rng(0), arm=True)
    plain = objects.pole(np.random.default_rng(0), arm=False)
    for o in (lamp, plain):
        assert inside(o.size[2], 5.0, 9.0) and inside(o.params["radius"], 0.08, 0.15)
    lo, hi = bbox(lamp.mesh)
    assert lo[1] < -0.9 and hi[1] <= lamp.params["radius"] + 1e-9
    assert inside(lamp.params["arm"], 1.0, 2.5)
    assert plain.size[1] == pytest.approx(2 * plain.params["radius"], rel=0.05)


@pytest.mark.parametrize("shape", objects.SIGN_SHAPES)
def test_sign_plate_faces_minus_y(shape: str) -> None:
    o = objects.sign(np.random.default_rng(3), shape=shape)
    assert inside(o.size[2], 2.2, 3.0) and inside(o.params["radius"], 0.03, 0.05)
    plate = o.meshes["plate"]
    lo, hi = bbox(plate)
    assert hi[1] - lo[1] == pytest.approx(0.02, abs=1e-9)  # 2 cm thick
    assert inside(max(hi[0] - lo[0], hi[2] - lo[2]), 0.6, 0.9)
    assert hi[1] < -o.params["radius"]  # in front of the pole, on the -y side
    V, T = plate.vertices, plate.triangles
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    front = n[:, 1] < 0
    assert np.allclose(V[T[front]][..., 1], lo[1])  # the -y facing face is the front face
    assert -n[front, 1].sum() == pytest.approx(n[n[:, 1] > 0, 1].sum())


def test_facade_blocks_right_of_the_baseline_with_recesses() -> None:
    x = np.linspace(0.0, 120.0, 40)
    base = np.column_stack([x, np.full_like(x, 5.0), np.full_like(x, 0.3)])
    m = objects.facade(base, 12.0, np.random.default_rng(4), depth=8.0)
    V = m.vertices
    y = V[:, 1] - 5.0
    assert y.max() <= 1e-9 and y.min() >= -8.0 - 1e-9  # road left (+y), buildings right
    assert V[:, 2].min() == pytest.approx(0.1) and V[:, 2].max() <= 0.1 + 0.2 + 1.3 * 12.0
    recess = np.unique(np.round(y[(y < -0.5 + 1e-9) & (y > -1.5 - 1e-9)], 6))
    assert len(recess) >= 1  # doorway recess back walls
    xs = np.unique(np.round(V[np.isclose(y, -8.0), 0], 6))  # block corners at the back
    assert 0.0 in xs and xs.max() <= 120.0 + 1e-9
    widths = np.diff(xs)
    assert widths.max() <= 20.0 + 1e-9
    again = objects.facade(base, 12.0, np.random.default_rng(4), depth=8.0)
    np.testing.assert_array_equal(again.vertices, V)


def test_facade_follows_a_curved_building_line() -> None:
    a = np.linspace(0.0, 1.0, 60)
    R = 60.0
    base = np.column_stack([R * np.sin(a), R - R * np.cos(a), np.zeros_like(a)])  # turns left
    m = objects.facade(base, 10.0, np.random.default_rng(1), depth=6.0)
    r = np.linalg.norm(m.vertices[:, :2] - [0.0, R], axis=1)
    # buildings lie outside the (left-turning) building line: radius >= chord's sagitta bound
    assert r.min() >= R - 20.0**2 / (8 * R) - 1e-6 and r.max() <= R + 6.0 + 1e-6
