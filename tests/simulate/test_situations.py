"""Situation streets (`situations.py`): the objects each is built around."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from app.core.labels import Semantic
from app.simulate.layout import build_scene
from app.simulate.meshes import foliage
from app.simulate.situations import TOUCHING_GAP, build_situation


def test_parked_rows_hold_long_vehicles_some_touching() -> None:
    """Buses, lorries and caravans stand in the parking lanes among vans and cars, and some
    stand closer to the next one than a clustering voxel (a row that clusters as one)."""
    scene = build_situation("parked_rows", 20.0, np.random.default_rng(4))
    parked = [b for b in scene.bodies if b.instance > 0 and not b.moving]
    names = {b.name for b in parked}
    assert {"parked-bus", "parked-truck", "caravan", "parked-car"} <= names
    caravans = [b for b in parked if b.name == "caravan"]
    assert all(b.semantic == Semantic.OTHER_VEHICLE for b in caravans)
    vehicles = [b for b in parked if b.semantic in (Semantic.CAR, Semantic.BUS, Semantic.TRUCK,
                                                    Semantic.OTHER_VEHICLE)]  # fmt: skip
    # gaps between neighbours along each parking lane (the street runs along x here)
    touching = 0
    for side in (-1, 1):
        row = np.array(
            sorted(
                (b.mesh.vertices[:, 0].min(), b.mesh.vertices[:, 0].max())
                for b in vehicles
                if np.sign(b.mesh.vertices[:, 1].mean()) == side
            )
        )
        gaps = row[1:, 0] - row[:-1, 1]
        assert (gaps > 0.05).all()  # never overlapping
        touching += int((gaps < TOUCHING_GAP + 0.05).sum())
    assert touching >= 1


def test_vegetation_adds_hedges_and_bushes_and_leaves_the_rest_of_the_street() -> None:
    """Town streets with `vegetation`: leafy hedges and bushes (SemanticKITTI vegetation) along
    the sidewalks, drawn after everything else, so the other objects are the seed's."""
    for build, name in ((build_situation, "shadow"), (build_scene, "urban")):
        plain = build(name, 30.0, np.random.default_rng(7))
        green = build(name, 30.0, np.random.default_rng(7), vegetation=True)
        assert [b.name for b in green.bodies[: len(plain.bodies)]] == [b.name for b in plain.bodies]
        assert all(
            np.array_equal(a.mesh.vertices, b.mesh.vertices)
            for a, b in zip(plain.bodies, green.bodies, strict=False)
        )
        plants = green.bodies[len(plain.bodies) :]
        assert {b.name for b in plants} == {"hedge", "bush"}
        assert all(b.semantic == Semantic.VEGETATION and b.instance > 0 for b in plants)
        # on the sidewalks, not in the road: every leaf beyond the parking lanes
        leaves = np.concatenate([b.mesh.vertices for b in plants])
        assert (
            np.abs(leaves[:, 1] - np.interp(leaves[:, 0], *plain.centerline[:, :2].T)).min() > 3.0
        )


def test_a_rays_way_into_foliage_is_scattered() -> None:
    """A hedge is leaves filling its volume, not a shell: rays along one line stop at depths
    spread over the hedge (a bush's scattered returns)."""
    rng = np.random.default_rng(0)
    hedge = foliage((2.0, 0.5, 0.75), rng, roundness=4.0)
    v = hedge.vertices
    assert len(hedge.triangles) > 1000
    assert (np.abs(v) <= np.array([2.0, 0.5, 0.75]) * 1.4 + 0.08).all()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(v.astype(np.float32), hedge.triangles.astype(np.uint32))
    ys = np.linspace(-1.5, 1.5, 40)
    zs = np.linspace(-0.5, 0.5, 20)
    origins = np.array([[x, -3.0, z] for x in ys for z in zs], np.float32)
    rays = np.hstack([origins, np.tile([0.0, 1.0, 0.0], (len(origins), 1))]).astype(np.float32)
    depth = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() - 3.0
    hit = np.isfinite(depth)
    assert 0.7 < hit.mean() < 1.0  # mostly stopped, some rays through the gaps
    assert np.percentile(depth[hit], 90) - np.percentile(depth[hit], 10) > 0.15
