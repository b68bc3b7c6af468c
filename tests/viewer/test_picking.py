"""Server-side picking: the brush ray meets the ground, the brush disc, camera projection, the
depth buffer that keeps hidden points out of a rectangle, and the click that takes the point
nearest the cursor on the front-most surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import viser.transforms as vtf

from app.geometry.ground import GroundModel
from app.store.pillar_labels import STORE_GRID
from app.viewer.modes.pillar_selection import RectangleOptions, rectangle_points
from app.viewer.picking import (
    ScreenCamera,
    pick_on_ray,
    pillars_in_disc,
    ray_ground_hit,
    visible,
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


@dataclass
class FakeCamera:
    """What the modes read of viser's CameraHandle."""

    wxyz: np.ndarray
    position: np.ndarray
    fov: float = np.pi / 2
    image_width: int = 800
    image_height: int = 800

    @property
    def aspect(self) -> float:
        return self.image_width / self.image_height


def looking_along_x(**kwargs) -> FakeCamera:
    wxyz = look_at_rotation(np.array([1.0, 0, 0]), np.array([0, 0, 1.0]))
    return FakeCamera(wxyz=wxyz, position=np.zeros(3), **kwargs)


def test_projection_follows_the_opencv_camera() -> None:
    screen = ScreenCamera.of(looking_along_x(image_width=1600, image_height=800))
    points = np.array(
        [
            [10.0, 0.0, 0.0],  # straight ahead
            [10.0, -2.0, 0.0],  # to the right (camera looks +x, up +z: right is -y)
            [10.0, 0.0, 2.0],  # above
            [-10.0, 0.0, 0.0],  # behind
        ]
    )
    px, depth = screen.project(points)
    np.testing.assert_allclose(px[0], [800.0, 400.0], atol=1e-9)
    assert px[1, 0] > 800.0 and abs(px[1, 1] - 400.0) < 1e-9
    assert px[2, 1] < 400.0  # screen y grows downwards
    # fov 90 degrees: a point at 45 degrees up lies on the top edge
    edge, _ = screen.project(np.array([[1.0, 0, 1.0]]))
    np.testing.assert_allclose(edge[0, 1], 0.0, atol=1e-9)
    assert (depth > 0).tolist() == [True, True, True, False]


def test_a_camera_not_reported_yet_gets_a_default_canvas() -> None:
    screen = ScreenCamera.of(looking_along_x(image_width=0, image_height=0))
    assert (screen.width, screen.height) == (1280, 720)


def wall_and_hidden_grid() -> tuple[np.ndarray, np.ndarray]:
    """A dense wall 10 m ahead (x = 10) and a grid of points behind it (x = 20), both
    spanning y, z in [-3, 3]: from the origin the wall hides the grid."""
    g = np.linspace(-3.0, 3.0, 61)
    yy, zz = np.meshgrid(g, g)
    wall = np.stack([np.full(yy.size, 10.0), yy.ravel(), zz.ravel()], axis=1)
    behind = wall + [10.0, 0.0, 0.0]
    return wall, behind


def test_depth_buffer_hides_points_behind_a_nearer_surface() -> None:
    wall, behind = wall_and_hidden_grid()
    seen = visible(np.concatenate([wall, behind]), ScreenCamera.of(looking_along_x()), 0.05)
    assert seen[: len(wall)].all()
    assert not seen[len(wall) :].any()
    # without the wall, the grid is seen
    assert visible(behind, ScreenCamera.of(looking_along_x()), 0.05).all()


def test_depth_buffer_sees_through_gaps() -> None:
    """A sparse fence (points 1 m apart) hides only what lies right behind its posts."""
    _, behind = wall_and_hidden_grid()
    posts = np.array([[10.0, y, z] for y in (-2.0, 2.0) for z in (-2.0, 2.0)])
    seen = visible(np.concatenate([posts, behind]), ScreenCamera.of(looking_along_x()), 0.05)
    assert seen[:4].all()
    assert seen[4:].mean() > 0.95


def test_rectangle_takes_only_visible_points_unless_asked() -> None:
    wall, behind = wall_and_hidden_grid()
    xyz = np.concatenate([wall, behind])
    camera = looking_along_x()
    everything = RectangleOptions(through=False, near=0.0, far=500.0)
    inside = rectangle_points(xyz, camera, (0.4, 0.4), (0.6, 0.6), 0.05, everything)
    assert inside[: len(wall)].any()
    assert not inside[len(wall) :].any()  # the grid hides behind the wall
    through = RectangleOptions(through=True, near=0.0, far=500.0)
    both = rectangle_points(xyz, camera, (0.4, 0.4), (0.6, 0.6), 0.05, through)
    assert both[len(wall) :].any() and (both[: len(wall)] == inside[: len(wall)]).all()
    # a depth range beyond the wall selects the grid (the wall does not hide outside its range)
    beyond = RectangleOptions(through=False, near=15.0, far=500.0)
    far = rectangle_points(xyz, camera, (0.4, 0.4), (0.6, 0.6), 0.05, beyond)
    assert not far[: len(wall)].any() and far[len(wall) :].any()
    # points outside the rectangle are never taken
    px, _ = ScreenCamera.of(camera).project(xyz)
    uv = px / 800.0
    assert ((uv[both] >= 0.4) & (uv[both] <= 0.6)).all()


def test_a_click_takes_the_point_nearest_the_cursor_on_the_front_surface() -> None:
    camera = looking_along_x()
    angle = 8.0 / ScreenCamera.of(camera).focal_px
    ray = np.array([1.0, 0.0, 0.0])
    points = np.array(
        [
            [12.0, 0.2, 0.0],  # the neighbouring slice, 0.2 m beside the ray, 2 m nearer
            [14.0, 0.01, 0.0],  # under the cursor
            [30.0, 0.0, 0.0],  # exactly on the ray, far behind
        ]
    )
    # the front-most surface near the ray is the neighbour at 12 m; the point under the
    # cursor at 14 m lies 2 m behind it, beyond the surface slack: the neighbour is taken
    assert pick_on_ray(points, np.zeros(3), ray, angle) == 0
    # on one surface (slices side by side at the same depth), the nearest on screen wins
    side_by_side = np.array([[14.0, 0.12, 0.0], [14.1, 0.01, 0.0], [30.0, 0.0, 0.0]])
    assert pick_on_ray(side_by_side, np.zeros(3), ray, angle) == 1
    # nothing within a few pixels: no pick
    assert pick_on_ray(np.array([[10.0, 1.0, 0.0]]), np.zeros(3), ray, angle) == -1


ANGLE = 0.01  # rad: about 5 pixels of a 720-pixel canvas at viser's default field of view


def test_pick_on_ray_takes_the_nearest_point_near_the_ray() -> None:
    points = np.array([[0, 0, 5.0], [0.05, 0, 2.0], [3, 0, 1.0], [0, 0, -4.0]])
    origin, down = np.array([0.0, 0.0, 10.0]), np.array([0.0, 0.0, -2.0])
    # first along the ray, not the nearest overall
    assert pick_on_ray(points, origin, down, ANGLE) == 0
    assert pick_on_ray(points[1:], origin, down, ANGLE) == 0  # 5 cm off the ray: still picked
    assert pick_on_ray(points[2:3], origin, down, ANGLE) == -1  # 3 m off the ray
    assert pick_on_ray(points[3:], np.array([0.0, 0.0, -10.0]), -down, ANGLE) == 0
    assert pick_on_ray(points[3:], origin, -down, ANGLE) == -1  # behind the camera
    assert pick_on_ray(np.zeros((0, 3)), origin, down, ANGLE) == -1
    # far away the tolerance grows with the distance (a click is a few pixels wide)
    far = np.array([[0.5, 0.0, -90.0]])
    assert pick_on_ray(far, origin, down, ANGLE) == 0
