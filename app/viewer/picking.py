"""Picking on the server: point clouds have no per-point click events in viser, so a click
arrives as a camera ray and a rectangle as screen corners, and the pillars are found here.

- Brush: the click ray meets the local ground surface (the map's ground height grid) where the
  height above ground first changes sign along the ray; every pillar whose centre lies within
  the brush radius of that spot is painted.
- Rectangle: points are projected with the client's camera (OpenCV convention as viser reports
  it: +Z forward, +Y down, vertical field of view) to normalised screen coordinates.
"""

from __future__ import annotations

import numpy as np
import viser.transforms as vtf

from app.geometry.ground import GroundModel
from app.store.pillar_labels import STORE_GRID

RAY_STEP = 0.1  # metres between samples along the click ray
RAY_REACH = 1000.0  # metres: farther than anything a map shows


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


def project_to_screen(
    points: np.ndarray,
    wxyz: np.ndarray,
    position: np.ndarray,
    fov: float,
    aspect: float,
) -> tuple[np.ndarray, np.ndarray]:
    """((n, 2) normalised screen coordinates, (n,) in front of the camera) of local points;
    (0, 0) is the top-left corner, (1, 1) the bottom-right."""
    rotation = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()  # camera -> world
    cam = (np.asarray(points, dtype=np.float64) - np.asarray(position)) @ rotation
    depth = cam[:, 2]
    front = depth > 1e-6
    safe = np.where(front, depth, 1.0)
    focal_y = 0.5 / np.tan(fov / 2.0)  # in screen heights
    u = 0.5 + cam[:, 0] / safe * focal_y / aspect
    v = 0.5 + cam[:, 1] / safe * focal_y
    return np.stack([u, v], axis=1), front


def in_screen_rect(
    points: np.ndarray,
    wxyz: np.ndarray,
    position: np.ndarray,
    fov: float,
    aspect: float,
    corner_min: tuple[float, float],
    corner_max: tuple[float, float],
) -> np.ndarray:
    """(n,) bool: the point projects inside the rectangle and lies in front of the camera."""
    uv, front = project_to_screen(points, wxyz, position, fov, aspect)
    lo = np.minimum(corner_min, corner_max)
    hi = np.maximum(corner_min, corner_max)
    return front & (uv >= lo).all(axis=1) & (uv <= hi).all(axis=1)
