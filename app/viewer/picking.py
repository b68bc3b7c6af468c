"""Picking on the server: point clouds have no per-point click events in viser, so a click
arrives as a camera ray and a rectangle as screen corners, and the pillars are found here.

- Brush: the click ray meets the local ground surface (the map's ground height grid) where the
  height above ground first changes sign along the ray; every pillar whose centre lies within
  the brush radius of that spot is painted.
- Rectangle: points are projected with the client's camera (OpenCV convention as viser reports
  it: +Z forward, +Y down, vertical field of view) to normalised screen coordinates, and only
  the points the browser shows are taken: a depth buffer of the shown points, each splatted as
  the disc viser draws for it, hides what lies behind a nearer surface (a facade behind a
  rectangle across the road is not selected through the road's points).
- Click on a point (review modes): the shown point nearest the cursor on screen, within a few
  pixels, on the surface drawn under the cursor (not the first point the ray grazes, which may
  belong to the neighbouring slice in front).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import viser.transforms as vtf

from app.geometry.ground import GroundModel
from app.store.pillar_labels import STORE_GRID

RAY_STEP = 0.1  # metres between samples along the click ray
RAY_REACH = 1000.0  # metres: farther than anything a map shows
PICK_PX = 8.0  # a click takes a point within this many screen pixels of the cursor ...
PICK_MIN_RADIUS = 0.05  # m: ... or within this distance of the ray (close-up views)
SURFACE_SLACK = (0.5, 0.05)  # m, share of depth: points this far behind the front-most one
# under the cursor (or in a depth-buffer cell) still belong to the surface seen there
DEPTH_BIN_PX = 3  # the depth buffer's cell, in screen pixels
MAX_SPLAT_BINS = 6  # a point hides at most this many cells around it (an 18 px disc)
FALLBACK_SCREEN = (1280, 720)  # pixels, while the browser has not reported its canvas yet


@dataclass(frozen=True)
class ScreenCamera:
    """The browser's camera as viser reports it, in pixels: what the user sees."""

    rotation: np.ndarray  # (3, 3) camera -> world (OpenCV axes: +Z forward, +Y down)
    position: np.ndarray  # (3,) scene coordinates
    fov: float  # vertical, radians
    width: int  # canvas pixels
    height: int

    @classmethod
    def of(cls, camera: Any) -> ScreenCamera:
        """From a viser `CameraHandle` (or anything with its attributes)."""
        width, height = int(camera.image_width), int(camera.image_height)
        if width <= 0 or height <= 0:
            width, height = FALLBACK_SCREEN
        return cls(
            rotation=vtf.SO3(np.asarray(camera.wxyz, dtype=np.float64)).as_matrix(),
            position=np.asarray(camera.position, dtype=np.float64),
            fov=float(camera.fov),
            width=width,
            height=height,
        )

    @property
    def focal_px(self) -> float:
        return 0.5 * self.height / float(np.tan(self.fov / 2.0))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((n, 2) pixel coordinates, (n,) depth along the view axis; <= 0 behind). Float32
        points (the shown clouds, sent as the browser draws them) are projected in float32,
        which rounds no coarser than the points already are, in a fraction of the time: a
        selection projects every shown point."""
        points = np.asarray(points)
        dtype = np.float32 if points.dtype == np.float32 else np.float64
        cam = (points - self.position.astype(dtype)) @ self.rotation.astype(dtype)
        depth = cam[:, 2]
        scale = dtype(self.focal_px) / np.where(depth > 1e-6, depth, dtype(1.0))
        px = np.empty((len(cam), 2), dtype=np.float64)
        np.multiply(cam[:, 0], scale, out=px[:, 0])
        np.multiply(cam[:, 1], scale, out=px[:, 1])
        px += (0.5 * self.width, 0.5 * self.height)
        return px, depth


def surface_slack(depth: np.ndarray | float) -> np.ndarray | float:
    """How far behind the front-most depth a point still counts as the surface seen there."""
    absolute, relative = SURFACE_SLACK
    return np.maximum(absolute, relative * np.asarray(depth))


def visible(
    points: np.ndarray,
    camera: ScreenCamera,
    point_size: float,
    projected: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(n,) bool: the point is in front of the camera, on the canvas and not hidden behind a
    nearer shown point. Every point is splatted into a depth buffer of DEPTH_BIN_PX cells as
    the disc viser draws (radius point_size * focal / depth pixels); a point is visible when
    its depth is within `surface_slack` of the nearest depth drawn over its cell. `projected`:
    the points' (pixels, depth) by `camera.project`, when the caller has them."""
    px, depth = camera.project(points) if projected is None else projected
    cols = -(-camera.width // DEPTH_BIN_PX)
    rows = -(-camera.height // DEPTH_BIN_PX)
    cell = np.floor(px / DEPTH_BIN_PX).astype(np.int64)
    on = (depth > 1e-6) & (cell[:, 0] >= 0) & (cell[:, 0] < cols)
    on &= (cell[:, 1] >= 0) & (cell[:, 1] < rows)
    result = np.zeros(len(depth), dtype=bool)
    idx = np.flatnonzero(on)
    if not len(idx):
        return result
    d, c = depth[idx], cell[idx]
    radius_px = point_size * camera.focal_px / d
    reach = np.clip(np.ceil(radius_px / DEPTH_BIN_PX - 0.5), 0, MAX_SPLAT_BINS).astype(np.int64)
    nearest = np.full(rows * cols, np.inf)
    flat = c[:, 1] * cols + c[:, 0]
    for r in np.flatnonzero(np.bincount(reach)).tolist():
        group = reach == r
        if r == 0:  # the common case (points smaller than a cell): each its own cell
            np.minimum.at(nearest, flat[group], d[group])
            continue
        gc, gd = c[group], d[group]
        for dx in range(-r, r + 1):
            for dy in range(-r, r + 1):
                if dx * dx + dy * dy > r * r + r:  # a disc of cells, not a square
                    continue
                x, y = gc[:, 0] + dx, gc[:, 1] + dy
                ok = (x >= 0) & (x < cols) & (y >= 0) & (y < rows)
                np.minimum.at(nearest, y[ok] * cols + x[ok], gd[ok])
    own = nearest[flat]
    result[idx] = d <= own + surface_slack(own)
    return result


def pick_on_ray(
    points: np.ndarray,
    origin: np.ndarray,
    direction: np.ndarray,
    angle: float,
    point_size: float = 0.0,
    min_radius: float = PICK_MIN_RADIUS,
) -> int:
    """Index of the point a click means, -1 for none. Candidates lie within `angle` of the
    click ray (PICK_PX over the focal length: a few pixels) or `min_radius` of it. The surface
    seen under the cursor is the front-most point whose drawn disc (radius `point_size`, as
    viser draws it) covers the cursor, else the front-most candidate; of the candidates on that
    surface (within `surface_slack` behind it) the one nearest the cursor on screen wins.
    Point clouds have no per-point click events in viser."""
    if not len(points):
        return -1
    d = np.asarray(direction, dtype=np.float64)
    norm = np.linalg.norm(d)
    if not norm > 0:
        return -1
    d = d / norm
    rel = np.asarray(points, dtype=np.float64) - np.asarray(origin, dtype=np.float64)
    t = rel @ d
    perp = np.sqrt(np.maximum(np.einsum("ij,ij->i", rel, rel) - t * t, 0.0))
    near = np.flatnonzero((t > 0) & (perp <= np.maximum(min_radius, t * angle)))
    if not len(near):
        return -1
    covering = near[perp[near] < point_size]
    front = float(t[covering if len(covering) else near].min())
    surface = near[t[near] <= front + surface_slack(front)]
    return int(surface[np.argmin(perp[surface] / t[surface])])


def click_angle(camera: Any) -> float:
    """PICK_PX as an angle from the click ray, for a viser camera."""
    return PICK_PX / ScreenCamera.of(camera).focal_px


def ray_ground_hit(
    ground: GroundModel,
    origin: np.ndarray,
    direction: np.ndarray,
    reach: float = RAY_REACH,
    step: float = RAY_STEP,
) -> np.ndarray | None:
    """(3,) where the ray first crosses the ground surface, or None when it never does."""
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    norm = np.linalg.norm(direction)
    if not norm > 0:
        return None
    direction = direction / norm
    t = np.arange(0.0, reach, step)
    samples = origin + t[:, None] * direction
    above = samples[:, 2] - ground.height(samples[:, :2])
    sign = np.sign(above)
    crossing = np.flatnonzero(sign[1:] != sign[:-1])
    if not len(crossing):
        return None
    i = int(crossing[0])
    a, b = above[i], above[i + 1]
    frac = a / (a - b) if a != b else 0.0
    return origin + (t[i] + frac * step) * direction


def pillars_in_disc(centre_world_xy: np.ndarray, radius: float) -> np.ndarray:
    """Store-grid ids of the pillars whose centre lies within `radius` of a world xy (at least
    the pillar under the centre)."""
    centre = np.asarray(centre_world_xy, dtype=np.float64)[:2]
    lo = STORE_GRID.cell_index((centre - radius)[None])[0]
    hi = STORE_GRID.cell_index((centre + radius)[None])[0]
    ix, iy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    ix, iy = ix.ravel(), iy.ravel()
    centres = STORE_GRID.cell_center(ix, iy)
    inside = np.hypot(*(centres - centre).T) <= radius
    under = STORE_GRID.cell_index(centre[None])[0]
    inside |= (ix == under[0]) & (iy == under[1])
    return np.asarray(STORE_GRID.cell_id(ix[inside], iy[inside]), dtype=np.int64)
