"""Server-side picking: the brush ray meets the ground, the brush disc, camera projection."""

from __future__ import annotations

import numpy as np
import viser.transforms as vtf

from app.geometry.ground import GroundModel
from app.store.pillar_labels import STORE_GRID
from app.viewer.picking import (
    in_screen_rect,
    pillars_in_disc,
    project_to_screen,
    ray_ground_hit,
)


def flat_ground(z: float, slope: float = 0.0) -> GroundModel:
    x = np.arange(-50.0, 51.0)
    heights = z + slope * np.repeat(x[:, None], len(x), axis=1)
    return GroundModel(origin=np.array([-50.0, -50.0]), cell=1.0, heights=heights)


def test_ray_meets_flat_ground_where_geometry_says() -> None:
    hit = ray_ground_hit(flat_ground(2.0), np.array([0.0, 0.0, 10.0]), np.array([1.0, 0, -1.0]))
    assert hit is not None
    np.testing.assert_allclose(hit, [8.0, 0.0, 2.0], atol=0.02)


def test_ray_meets_sloped_ground_on_the_slope() -> None:
    ground = flat_ground(0.0, slope=0.1)  # z = 0.1 x
    hit = ray_ground_hit(ground, np.array([0.0, 0.0, 20.0]), np.array([1.0, 0.0, -1.0]))
    assert hit is not None
    assert abs(hit[2] - 0.1 * hit[0]) < 0.02  # on the surface
    np.testing.assert_allclose(hit[0], 20.0 / 1.1, atol=0.05)


def test_ray_into_the_sky_misses() -> None:
    ground = flat_ground(0.0)
    assert ray_ground_hit(ground, np.array([0.0, 0.0, 5.0]), np.array([0.0, 0.3, 1.0])) is None
    assert ray_ground_hit(ground, np.array([0.0, 0.0, 5.0]), np.zeros(3)) is None


def test_brush_disc_holds_the_pillars_within_the_radius() -> None:
    centre = np.array([100.05, 200.05])
    cells = pillars_in_disc(centre, 1.0)
    ix, iy = STORE_GRID.decode(cells)
    distance = np.hypot(*(STORE_GRID.cell_center(ix, iy) - centre).T)
    assert (distance <= 1.0).all()
    assert abs(len(cells) - np.pi / 0.04) < 8  # ~ pi r^2 / cell area
    # every pillar centre within the radius is there (none missed at the square's corners)
    gx, gy = np.meshgrid(np.arange(490, 512), np.arange(990, 1012), indexing="ij")
    near = np.hypot(*(STORE_GRID.cell_center(gx.ravel(), gy.ravel()) - centre).T) <= 1.0
    assert near.sum() == len(cells)


def test_brush_of_zero_radius_paints_the_pillar_under_it() -> None:
    cells = pillars_in_disc(np.array([3.33, -7.71]), 0.0)
    assert cells.tolist() == [int(STORE_GRID.point_cell_ids(np.array([[3.33, -7.71]]))[0])]


def look_at_rotation(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """wxyz of a camera looking along `forward` (OpenCV: +Z forward, +Y down)."""
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return vtf.SO3.from_matrix(np.stack([x, y, z], axis=1)).wxyz


def test_projection_follows_the_opencv_camera() -> None:
    wxyz = look_at_rotation(np.array([1.0, 0, 0]), np.array([0, 0, 1.0]))  # looking along +x
    points = np.array(
        [
            [10.0, 0.0, 0.0],  # straight ahead
            [10.0, -2.0, 0.0],  # to the right (camera looks +x, up +z: right is -y)
            [10.0, 0.0, 2.0],  # above
            [-10.0, 0.0, 0.0],  # behind
        ]
    )
    uv, front = project_to_screen(points, wxyz, np.zeros(3), fov=np.pi / 2, aspect=2.0)
    np.testing.assert_allclose(uv[0], [0.5, 0.5], atol=1e-9)
    assert uv[1, 0] > 0.5 and abs(uv[1, 1] - 0.5) < 1e-9
    assert uv[2, 1] < 0.5  # screen y grows downwards
    # fov 90 degrees: a point at 45 degrees up lies on the top edge
    edge, _ = project_to_screen(np.array([[1.0, 0, 1.0]]), wxyz, np.zeros(3), np.pi / 2, 2.0)
    np.testing.assert_allclose(edge[0, 1], 0.0, atol=1e-9)
    assert front.tolist() == [True, True, True, False]


def test_rectangle_keeps_points_inside_and_in_front() -> None:
    wxyz = look_at_rotation(np.array([1.0, 0, 0]), np.array([0, 0, 1.0]))
    points = np.array([[10.0, 0.0, 0.0], [10.0, -9.0, 0.0], [-10.0, 0.0, 0.0]])
    inside = in_screen_rect(points, wxyz, np.zeros(3), np.pi / 2, 1.0, (0.6, 0.6), (0.4, 0.4))
    assert inside.tolist() == [True, False, False]
