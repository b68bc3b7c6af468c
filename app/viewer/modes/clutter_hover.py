"""Hover targets of the clutter review: where each instance of the frame is, under the pointer.

viser reports no hover to the server, but the browser outlines a clickable mesh while the
pointer is over it (its own yellow outline, drawn without a round trip). So each instance gets
an invisible clickable box round its points in 3D and, while the camera image is in the scene,
an invisible clickable slab over its box on the image (a few millimetres thick: the browser
outlines no flat face seen square on): hovering an instance outlines it where the pointer is (in
3D, or on the camera image), a click selects it (magenta in both views, as a click on one of
its points does), and a Ctrl-drag that starts on a slab draws a 2D box as one started on the
image does. Boxes and slabs are separate meshes: the browser draws transparent meshes far to
near by their geometry's centre, and an invisible face drawn before the image hides the image
behind it, so a slab (in front of the image) must be its own mesh, drawn after the image, and
while the image is in the scene a box that reaches near the camera (an object beside the car)
is left out. Faces point outwards and only they catch the pointer, so a box round the camera (a
wrongly merged structure along the street) catches nothing from inside it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from app.geometry.extents import label_extents
from app.viewer.modes.clutter_camera import BOX_LIFT, ImagePlane

MIN_BOX = 0.2  # metres: a box edge at least this long (a one-point piece is still a target)
REACH = 1.5  # with the image in the scene, a box nearer the camera than this x its depth has
# no target (it would hide the image)
TARGET_RGB = (255, 255, 255)
CORNER_BITS = np.arange(8)[:, None] >> np.arange(3) & 1  # a box's corner k: k's bits, x y z
# the 12 triangles of a box over its corners (bit 0: x high, bit 1: y high, bit 2: z high)
BOX_FACES = np.array([
    [0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
    [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5],
], dtype=np.uint32)  # fmt: skip
# shares of the image's depth between which an image target (a slab) lies, in front of it
SLAB = (BOX_LIFT, 0.999)


def instance_extents(
    values: np.ndarray, owner: np.ndarray, seen: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(instance indices, low, high): the extent of each instance's points' `values` (n, d),
    only of those `seen` when given, for the instances that have any."""
    keep = owner >= 0
    if seen is not None:
        keep &= seen
    low, high = label_extents(values[keep], owner[keep], int(owner[keep].max(initial=-1)) + 1)
    has = np.flatnonzero(np.isfinite(low[:, 0]))
    return has, low[has], high[has]


def facing(vertices: np.ndarray, faces: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """`faces` with each triangle wound counter-clockwise as seen from `towards` (n, 3): a
    point on the side its front should face."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", normal, towards - a) < 0
    out = faces.copy()
    out[flip] = out[flip][:, [0, 2, 1]]
    return out


def outward_faces(corners: np.ndarray) -> np.ndarray:
    """BOX_FACES wound so that each faces away from the middle of the 8 `corners` (in
    CORNER_BITS order)."""
    outward = corners[BOX_FACES].mean(axis=1) * 2 - corners.mean(axis=0)  # beyond each face
    return facing(corners, BOX_FACES, outward)


def box_mesh(low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a box round `low`-`high`, at least MIN_BOX a side, faces outwards."""
    centre = (low + high) / 2
    half = np.maximum(high - low, MIN_BOX) / 2
    corners = centre + np.where(CORNER_BITS == 1, half, -half)
    return corners, outward_faces(corners)


def reaches_image(plane: ImagePlane, low: np.ndarray, high: np.ndarray) -> bool:
    """Whether a box comes nearer the camera than REACH x the image's depth (or behind it)."""
    depth = plane.depth_of(np.where(CORNER_BITS == 1, high, low))
    return bool((depth < REACH * plane.depth).any())


class HoverTargets:
    """The frame's invisible instance targets, redrawn when they move."""

    def __init__(
        self,
        scene: Any,
        key: str,
        on_select: Callable[[int], None],
        on_drag: Callable[[Any], None],
    ):
        self.scene = scene
        self.key = key
        self.on_select = on_select
        self.on_drag = on_drag
        self.boxes: list[Any] = []
        self.quads: list[Any] = []
        self.drawn = b""

    def draw(
        self,
        xyz: np.ndarray,
        owner: np.ndarray,
        plane: ImagePlane | None,
        uv: np.ndarray | None,
        in_image: np.ndarray | None,
    ) -> None:
        """Boxes round each instance's points `xyz` (scene) and, with a `plane` shown, slabs
        over its box on the image (`uv` pixels, `in_image`); nothing is resent when nothing
        moved."""
        boxes = instance_extents(xyz, owner)
        if plane is not None:
            near = [reaches_image(plane, a, b) for _, a, b in zip(*boxes, strict=True)]
            boxes = tuple(x[~np.asarray(near, dtype=bool)] for x in boxes)
        quads = (np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)))
        if plane is not None and uv is not None and in_image is not None:
            quads = instance_extents(uv, owner, in_image)
        key = b"".join(np.round(a, 2).tobytes() for a in (*boxes, *quads))
        if key == self.drawn:
            return
        self.remove()
        self.drawn = key
        for k, a, b in zip(*boxes, strict=True):
            self.boxes.append(self._target(f"box{k}", int(k), *box_mesh(a, b)))
        if plane is None:
            return
        for k, (u0, v0), (u1, v1) in zip(*quads, strict=True):
            corners = np.array([  # CORNER_BITS: u high, v high, deeper
                plane.scene_point(u1 if bu else u0, v1 if bv else v0, SLAB[bd] * plane.depth)
                for bu, bv, bd in CORNER_BITS
            ])  # fmt: skip
            target = self._target(f"image{k}", int(k), corners, outward_faces(corners))
            target.on_drag("left", modifier="cmd/ctrl")(self.on_drag)
            self.quads.append(target)

    def _target(
        self, name: str, k: int, vertices: np.ndarray, faces: np.ndarray, side: str = "front"
    ) -> Any:
        mesh = self.scene.add_mesh_simple(
            f"/{self.key}/targets/{name}", vertices=vertices.astype(np.float32), faces=faces,
            color=TARGET_RGB, opacity=0.0, side=side, cast_shadow=False, receive_shadow=False,
        )  # fmt: skip
        mesh.on_click(lambda _: self.on_select(k))
        return mesh

    def remove(self) -> None:
        for node in self.boxes + self.quads:
            node.remove()
        self.boxes, self.quads = [], []
        self.drawn = b""
