"""Hover targets of the clutter review: where each instance of the frame is, under the pointer.

viser reports no hover to the server, but the browser outlines a clickable mesh while the
pointer is over it (its own yellow outline, drawn without a round trip). So each instance gets
an invisible clickable box round its points in 3D and, while the camera image is in the scene,
an invisible clickable quad over its box on the image: hovering an instance outlines it where
the pointer is, a click selects it (magenta in both views, as a click on one of its points
does), and a Ctrl-drag that starts on an image target draws a 2D box as one started on the
image does. Transparent meshes are drawn after the points, so the invisible boxes hide none;
the boxes show their outer faces only, so one round the camera (a wrongly merged structure
along the street) catches no pointer from inside it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from app.viewer.modes.clutter_camera import BOX_LIFT, ImagePlane

MIN_BOX = 0.2  # metres: a box edge at least this long (a one-point piece is still a target)
TARGET_RGB = (255, 255, 255)


def instance_extents(
    values: np.ndarray, owner: np.ndarray, seen: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(instance indices, low, high): the extent of each instance's points' `values` (n, d),
    only of those `seen` when given, for the instances that have any."""
    keep = owner >= 0
    if seen is not None:
        keep &= seen
    values = np.asarray(values, dtype=np.float64)
    n = int(owner[keep].max(initial=-1)) + 1
    low = np.full((n, values.shape[1]), np.inf)
    high = np.full((n, values.shape[1]), -np.inf)
    np.minimum.at(low, owner[keep], values[keep])
    np.maximum.at(high, owner[keep], values[keep])
    has = np.flatnonzero(np.isfinite(low[:, 0]))
    return has, low[has], high[has]


class HoverTargets:
    """The frame's invisible instance boxes (3D) and image quads, redrawn when they move."""

    def __init__(
        self,
        scene: Any,
        key: str,
        on_select: Callable[[int], None],
        on_image_drag: Callable[[Any], None],
    ):
        self.scene = scene
        self.key = key
        self.on_select = on_select
        self.on_image_drag = on_image_drag
        self.boxes: list[Any] = []
        self.quads: list[Any] = []
        self.drawn: tuple[bytes, bytes] = (b"", b"")

    def draw(
        self,
        xyz: np.ndarray,
        owner: np.ndarray,
        plane: ImagePlane | None,
        uv: np.ndarray | None,
        in_image: np.ndarray | None,
    ) -> None:
        """Boxes round each instance's points `xyz` (scene) and, with a `plane` shown, quads over
        its box on the image (`uv` pixels, `in_image`); nothing is resent when nothing moved."""
        boxes = instance_extents(xyz, owner)
        quads = (np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)))
        if plane is not None and uv is not None and in_image is not None:
            quads = instance_extents(uv, owner, in_image)
        key = (
            b"".join(np.round(a, 2).tobytes() for a in boxes),
            b"".join(np.round(a, 1).tobytes() for a in quads),
        )
        if key == self.drawn:
            return
        self.remove()
        self.drawn = key
        for k, a, b in zip(*boxes, strict=True):
            box = self.scene.add_box(
                f"/{self.key}/targets/box{k}", color=TARGET_RGB,
                dimensions=tuple(np.maximum(b - a, MIN_BOX)), position=tuple((a + b) / 2),
                opacity=0.0, side="front", cast_shadow=False, receive_shadow=False,
            )  # fmt: skip
            box.on_click(lambda _, k=int(k): self.on_select(k))
            self.boxes.append(box)
        if plane is None:
            return
        depth = plane.depth * (1.0 + BOX_LIFT) / 2  # on the image, under a box being drawn
        for k, (u0, v0), (u1, v1) in zip(*quads, strict=True):
            corners = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
            quad = self.scene.add_mesh_simple(
                f"/{self.key}/targets/image{k}",
                vertices=np.array([plane.scene_point(u, v, depth) for u, v in corners], np.float32),
                faces=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32), color=TARGET_RGB,
                opacity=0.0, side="double", cast_shadow=False, receive_shadow=False,
            )  # fmt: skip
            quad.on_click(lambda _, k=int(k): self.on_select(k))
            quad.on_drag("left", modifier="cmd/ctrl")(self.on_image_drag)
            self.quads.append(quad)

    def remove(self) -> None:
        for node in self.boxes + self.quads:
            node.remove()
        self.boxes, self.quads = [], []
        self.drawn = (b"", b"")
