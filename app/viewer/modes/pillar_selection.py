"""A pillar selection waiting for the user's confirmation, and the depth-aware rectangle.

A rectangle takes the pillars of the shown points inside it that the user can see (not those
behind a nearer surface, unless "select hidden points too" is ticked) within the chosen depth
range. A small selection is labelled at once; a large one (more than CONFIRM_ABOVE pillars) is
drawn as a green preview and written only when the user presses Enter (Esc drops it), with
the class picked at that moment, so a drag across a street never relabels a facade unseen.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from app.viewer.modes.pillar_tools import points_in_polygon
from app.viewer.picking import (
    DEPTH_BIN_PX,
    MAX_SPLAT_BINS,
    ScreenCamera,
    visible,
)

CONFIRM_ABOVE = 400  # pillars: larger selections wait for Enter (16 m2 of 0.2 m pillars)
PREVIEW_RGB = (40, 215, 60)  # green: no pillar class uses it
PREVIEW_SCALE = 1.6  # preview points are drawn this much larger than the map's


@dataclass(frozen=True)
class RectangleOptions:
    through: bool  # take hidden points too
    near: float  # metres from the camera
    far: float


def rectangle_points(
    xyz: np.ndarray,
    camera: Any,
    corner_min: tuple[float, float],
    corner_max: tuple[float, float],
    point_size: float,
    options: RectangleOptions,
    outline: np.ndarray | None = None,
) -> np.ndarray:
    """(n,) bool over `xyz` (the shown points): inside the rectangle (and inside `outline`, a
    closed polygon in screen pixels within it: the polygon's and the lasso's test), within the
    depth range and, unless `options.through`, visible (`picking.visible`). The points are
    projected once."""
    screen = ScreenCamera.of(camera)
    size = np.array([screen.width, screen.height], dtype=np.float64)
    lo = np.minimum(corner_min, corner_max) * size  # pixels
    hi = np.maximum(corner_min, corner_max) * size
    px, depth = screen.project(xyz)
    # points just outside the rectangle may hide points inside it: they join the depth buffer
    margin = MAX_SPLAT_BINS * DEPTH_BIN_PX
    u, v = px[:, 0], px[:, 1]  # one comparison per column: every shown point passes here
    near_rect = (u >= lo[0] - margin) & (u <= hi[0] + margin)
    near_rect &= (v >= lo[1] - margin) & (v <= hi[1] + margin)
    near_rect &= (depth > 1e-6) & (depth >= options.near) & (depth <= options.far)
    idx = np.flatnonzero(near_rect)
    u, v = u[idx], v[idx]
    inside = (u >= lo[0]) & (u <= hi[0]) & (v >= lo[1]) & (v <= hi[1])
    if outline is not None:
        k = np.flatnonzero(inside)
        inside[k] = points_in_polygon(px[idx[k]], outline)
    if not options.through:
        inside &= visible(xyz[idx], screen, point_size, (px[idx], depth[idx]))
    result = np.zeros(len(xyz), dtype=bool)
    result[idx[inside]] = True
    return result


class PendingSelection:
    """Pillars selected and not yet written, drawn as a preview cloud of their shown points."""

    def __init__(self, scene: Any, node: str, cells: np.ndarray, how: str):
        self.scene = scene
        self.node = node
        self.cells = cells  # store cell ids
        self.how = how
        self.cloud: Any = None

    def draw(self, xyz: np.ndarray, point_size: float) -> None:
        """(Re)draw the preview over `xyz` (the shown points of the selected pillars)."""
        self.remove()
        if len(xyz):
            self.cloud = self.scene.add_point_cloud(
                self.node,
                points=xyz,
                colors=PREVIEW_RGB,
                point_size=PREVIEW_SCALE * point_size,
                precision="float32",
                point_shading="flat",
            )

    def resize(self, point_size: float) -> None:
        if self.cloud is not None:
            self.cloud.point_size = PREVIEW_SCALE * point_size

    def remove(self) -> None:
        if self.cloud is not None:
            self.cloud.remove()
            self.cloud = None
