"""RayCaster: exact static hits, body/triangle ids, phantoms of moving bodies, halo returns."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.labels import Semantic
from app.simulate.colors import COLORS
from app.simulate.raycast import RayCaster, inflate
from app.simulate.scene import Body, Mesh, Motion, Scene

# A box with 8 shared vertices, counter-clockwise seen from outside; two triangles per face in
# the order -x, +x, -y, +y, -z, +z (triangle 2f and 2f+1 belong to face f).
FACES = {"-x": [0, 4, 6, 2], "+x": [1, 3, 7, 5], "-y": [0, 1, 5, 4],
         "+y": [2, 6, 7, 3], "-z": [0, 2, 3, 1], "+z": [4, 5, 7, 6]}  # fmt: skip
BOX_TRIANGLES = np.array([[[q[0], q[1], q[2]], [q[0], q[2], q[3]]] for q in FACES.values()])


def box_mesh(lo, hi) -> Mesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array(
        [[(lo, hi)[i & 1][0], (lo, hi)[i >> 1 & 1][1], (lo, hi)[i >> 2][2]] for i in range(8)]
    )
    return Mesh(corners, BOX_TRIANGLES)


def plane_mesh(x0, x1, y0, y1, z=0.0) -> Mesh:
    v = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    return Mesh(np.array(v), np.array([[0, 1, 2], [0, 2, 3]]))


def body(name, mesh, semantic=Semantic.ROAD, instance=0, motion=None, halo=0.0, refl=0.3) -> Body:
    return Body(name, mesh, int(semantic), instance, COLORS[semantic], refl, motion, -1, halo)


def scene_of(bodies: list[Body]) -> Scene:
    path = Motion(np.array([0.0, 1.0]), np.zeros((2, 3)), np.zeros(2))
    return Scene("test", 0, bodies, np.array([[-50.0, 0, 0], [50.0, 0, 0]]), path, 1.0)


def linear_motion(start, velocity, t0=-10.0, t1=10.0, yaw=0.0) -> Motion:
    times = np.array([t0, t1])
    start, velocity = np.asarray(start, float), np.asarray(velocity, float)
    return Motion(times, start + np.outer(times, velocity), np.full(2, yaw))


def box_distance(p: np.ndarray, lo, hi) -> np.ndarray:
    """Signed distance of points to an axis-aligned box (negative inside)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_static_plane_gives_exact_ranges():
    caster = RayCaster(scene_of([body("road", plane_mesh(-500, 500, -500, 500))]))
    rng = np.random.default_rng(0)
    n = 5000
    d = unit(rng.normal(size=(n, 3)) * [1, 1, 0.3] - [0, 0, 0.2])
    d = d[d[:, 2] < -0.02]
    h = 2.4
    o = np.tile([120.0, -30.0, h], (len(d), 1))
    hits = caster.cast(o, d, np.zeros(len(d)), 1000.0, rng)
    expected = h / -d[:, 2]
    inside = np.all(np.abs(o[:, :2] + expected[:, None] * d[:, :2]) < 499, axis=1)
    assert np.all(hits.body[inside] == 0)
    np.testing.assert_allclose(hits.distance[inside], expected[inside], rtol=2e-6, atol=1e-5)
    np.testing.assert_allclose(hits.normal[inside], np.tile([0, 0, 1.0], (inside.sum(), 1)))
    assert not hits.halo.any()
    # beyond max_range is a miss
    short = caster.cast(o, d, np.zeros(len(d)), 10.0, rng)
    assert np.all(short.body[expected > 10] == -1)
    assert np.all(np.isinf(short.distance[expected > 10]))
    assert np.all(short.triangle[expected > 10] == -1)


def slab_entry(o: np.ndarray, d: np.ndarray, lo, hi):
    """Entry distance and entry face (0..5: -x, +x, -y, +y, -z, +z) of rays into a box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
    enter, leave = near.max(axis=1), far.min(axis=1)
    axis = near.argmax(axis=1)
    face = 2 * axis + (d[np.arange(len(d)), axis] < 0)
    second = np.sort(near, axis=1)[:, -2]
    clear = (enter - second > 1e-3) & (leave - enter > 1e-3)  # not next to an edge
    return np.where((enter <= leave) & (enter > 0), enter, np.inf), face, clear


def test_ray_grid_hits_box_with_right_body_and_triangle():
    lo, hi = (10.0, -1.0, 0.0), (14.0, 1.0, 1.5)
    bodies = [
        body("road", plane_mesh(-50, 50, -50, 50, z=-0.01)),
        body("house", box_mesh((30, 20, 0), (31, 21, 1)), Semantic.BUILDING),
        body("car", box_mesh(lo, hi), Semantic.CAR, instance=7),
    ]
    caster = RayCaster(scene_of(bodies))
    y, z = np.meshgrid(np.linspace(-2, 2, 81), np.linspace(0.05, 2.5, 50))
    n = y.size
    o = np.zeros((n, 3))
    o[:, 2] = 3.0  # above the roof: rays meet the front (-x), side and top (+z) faces
    d = unit(np.stack([np.full(n, 10.0), y.ravel(), z.ravel() - 3.0], axis=1))
    hits = caster.cast(o, d, 0.0, 100.0, np.random.default_rng(0))
    enter, face, clear = slab_entry(o, d, lo, hi)
    on_box = np.isfinite(enter) & clear
    assert on_box.sum() > 500
    assert set(face[on_box]) == {0, 5}
    assert np.all(hits.body[on_box] == 2)
    np.testing.assert_array_equal(hits.triangle[on_box] // 2, face[on_box])
    np.testing.assert_allclose(hits.distance[on_box], enter[on_box], atol=1e-4)
    expected_normal = np.array([[-1.0, 0, 0], [0, 0, 1.0]])[face[on_box] // 5]
    np.testing.assert_allclose(hits.normal[on_box], expected_normal, atol=1e-7)
    # rays clear of the box hit the road (or the sky)
    clear_of_box = ~np.isfinite(slab_entry(o, d, np.subtract(lo, 1e-3), np.add(hi, 1e-3))[0])
    assert clear_of_box.sum() > 500
    assert set(np.unique(hits.body[clear_of_box])) <= {-1, 0}
    hit = hits.body >= 0
    assert np.all(np.einsum("ij,ij->i", hits.normal, d)[hit] <= 0)
    np.testing.assert_allclose(np.linalg.norm(hits.normal[hit], axis=1), 1.0)


def test_moving_body_matches_brute_force_per_time():
    """Per-ray time placement and culling agree with casting a world copy of the box at each
    ray's time (rays shuffled, so culling blocks span every time and direction)."""
    lo, hi = np.array([-2.0, -0.9, 0.0]), np.array([2.0, 0.9, 1.5])
    motion = linear_motion([5.0, 8.0, 0.0], [0.0, -15.0, 0.0], yaw=0.3)
    bodies = [
        body("road", plane_mesh(-60, 60, -60, 60)),
        body("car", box_mesh(lo, hi), Semantic.CAR, instance=3, motion=motion),
    ]
    caster = RayCaster(scene_of(bodies), chunk_size=5000)
    rng = np.random.default_rng(1)
    n_times, per_time = 12, 3000
    times = np.repeat(np.linspace(0.0, 1.0, n_times), per_time)
    d = unit(rng.normal(size=(len(times), 3)) * [1, 1, 0.25])
    o = np.tile([0.0, 0.0, 1.0], (len(times), 1))
    perm = rng.permutation(len(times))
    hits = caster.cast(o[perm], d[perm], times[perm], 80.0, rng)
    inv = np.argsort(perm)
    dist, bod = hits.distance[inv], hits.body[inv]
    for k, t in enumerate(np.linspace(0.0, 1.0, n_times)):
        T = motion.local_to_world(t)
        world_box = box_mesh(lo, hi).transformed(T[:3, :3], T[:3, 3])
        ref = RayCaster(scene_of([bodies[0], body("car", world_box, Semantic.CAR, 3)]))
        sl = slice(k * per_time, (k + 1) * per_time)
        expect = ref.cast(o[sl], d[sl], t, 80.0, rng)
        np.testing.assert_array_equal(bod[sl], expect.body)
        np.testing.assert_allclose(dist[sl], expect.distance, atol=2e-4)
        assert (expect.body == 1).sum() > 0


def test_cast_is_independent_of_chunking():
    motion = linear_motion([8.0, 0.0, 0.0], [0.0, 12.0, 0.0])
    bodies = [
        body("road", plane_mesh(-60, 60, -60, 60)),
        body("car", box_mesh((-2, -1, 0), (2, 1, 1.5)), Semantic.CAR, 1, motion),
    ]
    rng = np.random.default_rng(2)
    n = 20000
    d = unit(rng.normal(size=(n, 3)) * [1, 1, 0.2])
    o = np.tile([0.0, 0.0, 1.7], (n, 1))
    t = np.sort(rng.uniform(0, 0.5, n))
    a = RayCaster(scene_of(bodies), chunk_size=1_000_000).cast(o, d, t, 100.0)
    b = RayCaster(scene_of(bodies), chunk_size=777).cast(o, d, t, 100.0)
    np.testing.assert_array_equal(a.body, b.body)
    np.testing.assert_array_equal(a.triangle, b.triangle)
    np.testing.assert_array_equal(a.distance, b.distance)
    assert (a.body == 1).sum() > 50


def test_inflate_moves_surface_out_by_at_most_margin():
    lo, hi = (-2.0, -1.0, 0.0), (2.0, 1.0, 1.5)
    # a box made of separate faces (24 vertices) and wound inside-out: inflation still goes out
    mesh = box_mesh(lo, hi)
    soup = Mesh(mesh.vertices[mesh.triangles].reshape(-1, 3), np.arange(36).reshape(12, 3)[:, ::-1])
    for m in (mesh, soup):
        fat = inflate(m, 0.25)
        sd = box_distance(fat.vertices, lo, hi)
        np.testing.assert_allclose(sd, 0.25, atol=1e-9)  # every vertex moved exactly 0.25 out


def halo_scene(p: float, margin: float = 0.3, moving: bool = True):
    lo, hi = np.array([-2.0, -0.9, 0.0]), np.array([2.0, 0.9, 1.5])
    motion = linear_motion([10.0, 0.0, 0.0], [0.0, 0.0, 0.0]) if moving else None
    mesh = box_mesh(lo, hi) if moving else box_mesh(lo + [10, 0, 0], hi + [10, 0, 0])
    bodies = [
        body("road", plane_mesh(-60, 60, -60, 60, z=-0.5)),
        body("car", mesh, Semantic.CAR, 1, motion, halo=margin),
        body("van", box_mesh((-2.5, 4.0, 0.0), (2.5, 6.0, 2.0)), Semantic.OTHER_VEHICLE, 2),
    ]
    return RayCaster(scene_of(bodies), halo_probability=p), lo + [10, 0, 0], hi + [10, 0, 0]


@pytest.mark.parametrize("moving", [True, False])
def test_halo_points_only_near_halo_body_within_margin(moving):
    caster, lo, hi = halo_scene(0.5, moving=moving)
    rng = np.random.default_rng(3)
    az, el = np.meshgrid(np.radians(np.linspace(-60, 60, 1201)), np.radians(np.linspace(-8, 8, 81)))
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    o = np.tile([0.0, 0.0, 0.75], (len(d), 1))
    hits = caster.cast(o, d, 0.0, 100.0, rng)
    assert hits.halo.sum() > 100
    assert np.all(hits.body[hits.halo] == 1)
    hit = hits.body >= 0
    p = np.where(hit[:, None], o + np.where(hit, hits.distance, 0.0)[:, None] * d, np.nan)
    sd = box_distance(p[hits.halo], lo, hi)
    assert np.all(sd > -1e-4)
    assert np.all(sd <= 0.3 + 1e-4)
    # about half of the rays that graze the halo without touching the car become halo returns
    grazing = caster.cast(o, d, 0.0, 100.0, rng)
    fat = RayCaster(scene_of([body("fat", inflate(box_mesh(lo, hi), 0.3), Semantic.CAR, 1)]))
    fat_hits = fat.cast(o, d, 0.0, 100.0)
    n_graze = ((fat_hits.body == 0) & (grazing.body != 1) | grazing.halo).sum()
    assert 0.35 < grazing.halo.sum() / n_graze < 0.65
    # points on the car surface itself are exact
    surf = (hits.body == 1) & ~hits.halo
    assert np.abs(box_distance(p[surf], lo, hi)).max() < 1e-4
    # no halo when disabled
    assert not caster.cast(o, d, 0.0, 100.0, rng, with_halo=False).halo.any()
    none, _, _ = halo_scene(0.0, moving=moving)
    assert not none.cast(o, d, 0.0, 100.0, rng).halo.any()


def test_halo_is_deterministic_given_rng():
    caster, _, _ = halo_scene(0.5)
    az = np.radians(np.linspace(-30, 30, 5000))
    d = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], -1)
    o = np.tile([0.0, 0.0, 0.75], (len(d), 1))
    a = caster.cast(o, d, 0.0, 100.0, np.random.default_rng(9))
    b = caster.cast(o, d, 0.0, 100.0, np.random.default_rng(9))
    np.testing.assert_array_equal(a.halo, b.halo)
    np.testing.assert_array_equal(a.distance, b.distance)


def grid_terrain(n: int, size: float) -> Mesh:
    x, y = np.meshgrid(np.linspace(-size, size, n), np.linspace(-size, size, n))
    z = 0.5 * np.sin(0.3 * x) * np.cos(0.2 * y)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, e = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:]
    tri = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, e.ravel()], 1)])
    return Mesh(np.stack([x.ravel(), y.ravel(), z.ravel()], 1), tri)


def test_many_static_rays_on_a_large_mesh():
    """A million rays on ~100k triangles: every downward ray lands on the terrain."""
    terrain = grid_terrain(225, 100.0)
    caster = RayCaster(scene_of([body("terrain", terrain, Semantic.TERRAIN)]))
    rng = np.random.default_rng(4)
    n = 1_000_000
    d = unit(rng.normal(size=(n, 3)) * [1, 1, 0.3] - [0, 0, 0.5])
    o = np.tile([3.0, 2.0, 3.0], (n, 1))
    hits = caster.cast(o, d, 0.0, 200.0)
    down = d[:, 2] < -0.2
    assert np.all(hits.body[down] == 0)


def test_more_bodies_than_live_scenes_cast_alike():
    """Bodies cast in their own frames get open3d scenes on demand, a bounded number alive
    (each holds an Embree device; a process crashes after one or two thousand): 40 moving and
    parked cars with halos cast through a cache of 3 scenes give the hits of an unbounded one."""
    bodies = [body("road", plane_mesh(-200, 200, -20, 20))]
    for k in range(20):
        motion = linear_motion([-190.0 + 19 * k, 3.0, 0.0], [8.0, 0.0, 0.0])
        bodies.append(body("car", box_mesh((-2, -1, 0), (2, 1, 1.5)), Semantic.CAR, k + 1, motion,
                           halo=0.2))  # fmt: skip
        lo = np.array([-190.0 + 19 * k, -6.0, 0.0])
        bodies.append(body("parked", box_mesh(lo, lo + [4, 2, 1.5]), Semantic.CAR, 100 + k,
                           halo=0.2))  # fmt: skip
    rng = np.random.default_rng(3)
    n = 40_000
    t = np.sort(rng.uniform(0, 4, n))
    o = np.column_stack([-200 + 100 * t, np.zeros(n), np.full(n, 1.7)])  # a van driving along
    d = unit(rng.normal(size=(n, 3)) * [1, 1, 0.15])
    unbounded = RayCaster(scene_of(bodies))
    bounded = RayCaster(scene_of(bodies))
    bounded._scenes.size = 3
    a = unbounded.cast(o, d, t, 60.0, np.random.default_rng(0))
    b = bounded.cast(o, d, t, 60.0, np.random.default_rng(0))
    for name in ("body", "triangle", "distance", "halo"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert len(np.unique(a.body[a.body > 0])) > 10 and a.halo.any()
    assert len(bounded._scenes._scenes) == 3
