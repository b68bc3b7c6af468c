"""The camera image in the 3D view (clutter review), on the rays its pixels see, and the 2D
boxes a reviewer draws on it.

viser's GUI images take no pointer events, but a scene image reports drags (start, pointer
updates, end). So the frame's camera image, with the instances drawn over it, is placed in the
scene `IMAGE_DEPTH` in front of the camera's optical centre, oriented and sized by the camera's
calibration (`geometry.projection.camera_pose`): seen from the optical centre ("Look through the
camera") every pixel lies over the LiDAR points it sees. A Ctrl-drag on it spans a box whose
corners are the pixels under the pointer (the pointer's ray from the viewer's camera meets the
image's plane), drawn on the image as it grows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import viser.transforms as vtf

from app.geometry.projection import CameraPose
from app.viewer.picking import ScreenCamera

IMAGE_DEPTH = 1.0  # metres in front of the camera: nearer than any point it sees (the
# scanner never sees its own car), so looking through the camera nothing covers the image
BOX_LIFT = 0.995  # the box's outline is drawn this share of the image's depth (in front of it)


@dataclass(frozen=True)
class ImagePlane:
    """A camera image placed in the scene: camera axes OpenCV (+X right, +Y down, +Z forward)."""

    rotation: np.ndarray  # (3, 3) camera -> scene
    centre: np.ndarray  # (3,) the optical centre in scene coordinates
    K: np.ndarray  # (3, 3)
    width: int  # image pixels
    height: int
    depth: float = IMAGE_DEPTH

    @classmethod
    def of(
        cls,
        camera: CameraPose,
        sensor_to_world: np.ndarray,
        origin: np.ndarray,
        width: int,
        height: int,
        depth: float = IMAGE_DEPTH,
    ) -> ImagePlane:
        """The camera of a frame whose sensor pose is `sensor_to_world` (4x4), in a scene
        re-centred on `origin`."""
        R, t = sensor_to_world[:3, :3], sensor_to_world[:3, 3]
        return cls(
            rotation=R @ camera.rotation,
            centre=R @ camera.centre + t - origin,
            K=camera.K,
            width=width,
            height=height,
            depth=depth,
        )

    def scene_point(self, u: float, v: float, depth: float | None = None) -> np.ndarray:
        """(3,) where pixel (u, v) lies on the image (or at `depth` along its ray)."""
        ray = np.linalg.solve(self.K, np.array([u, v, 1.0]))
        return self.centre + self.rotation @ (ray * (self.depth if depth is None else depth))

    def depth_of(self, points: np.ndarray) -> np.ndarray:
        """Depth along the camera's view of scene points (..., 3)."""
        return (np.asarray(points, dtype=np.float64) - self.centre) @ self.rotation[:, 2]

    def holds(self, point: np.ndarray, tolerance: float = 0.01) -> bool:
        """Whether a scene point lies on the image's plane (within `tolerance` of its depth)."""
        return abs(float(self.depth_of(point)) - self.depth) <= tolerance * self.depth

    def node_pose(self) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(wxyz, position, render width, render height) of the viser image that shows it: an
        image node spans its render size centred on its position, rows along its +Y."""
        fx, fy = self.K[0, 0], self.K[1, 1]
        centre = self.scene_point(self.width / 2.0, self.height / 2.0)
        wxyz = vtf.SO3.from_matrix(self.rotation).wxyz
        return wxyz, centre, self.width * self.depth / fx, self.height * self.depth / fy

    def pixel_of(self, point: np.ndarray) -> tuple[float, float] | None:
        """(u, v) of a scene point seen by the camera (None behind it)."""
        cam = self.rotation.T @ (np.asarray(point, dtype=np.float64) - self.centre)
        if cam[2] <= 1e-9:
            return None
        uvw = self.K @ cam
        return float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2])

    def pixel_under(
        self, screen: ScreenCamera, screen_pos: tuple[float, float]
    ) -> tuple[float, float] | None:
        """(u, v) of the image under the pointer at `screen_pos` (0-1 of the canvas), where the
        pointer's ray from the viewer's camera meets the image's plane (None: it does not)."""
        sx, sy = screen_pos
        f = screen.focal_px
        ray_cam = np.array(
            [(sx * screen.width - 0.5 * screen.width) / f,
             (sy * screen.height - 0.5 * screen.height) / f, 1.0]
        )  # fmt: skip
        ray = screen.rotation @ ray_cam
        normal = self.rotation[:, 2]
        facing = float(normal @ ray)
        if abs(facing) < 1e-9:
            return None
        t = float(normal @ (self.centre + self.depth * normal - screen.position)) / facing
        if t <= 0:
            return None
        return self.pixel_of(screen.position + t * ray)

    def box_outline(self, a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
        """(4, 2, 3) line segments of the box with pixel corners `a` and `b`, just in front of
        the image."""
        (u0, v0), (u1, v1) = a, b
        corners = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
        points = np.array([self.scene_point(u, v, self.depth * BOX_LIFT) for u, v in corners])
        return np.stack([points, np.roll(points, -1, axis=0)], axis=1)

    def viewing_fov(self, aspect: float) -> float:
        """The vertical field of view (radians) that shows the whole image from its optical
        centre on a canvas of `aspect` (width / height)."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        half_w = max(cx, self.width - cx) / fx  # tangents of the half angles the image spans
        half_h = max(cy, self.height - cy) / fy
        return float(2.0 * np.arctan(max(half_h, half_w / max(aspect, 1e-6)) * 1.02))
