"""Mask images of clutter review units: the image crop around an instance with its mask
component tinted in its class colour and its points dotted, white where the pipeline removes
them, black where it keeps them; for instances outside the image a top view of the frame around
it, its points red / cyan."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from app.pipelines.clutter.segmenter import CLUTTER_CLASSES, CLUTTER_COLORS

CROP_PAD_PX = 16  # context around an instance's pixels in its mask image
TOP_VIEW_PX = 256  # side of the top view of an instance outside the image
# point colours: on the image (over the class tint) and on the top view (over grey points)
IMAGE_RGB = {True: (255, 255, 255), False: (0, 0, 0)}  # removed by the pipeline / kept
TOP_RGB = {True: (255, 40, 40), False: (0, 230, 230)}


def mask_crop(
    image: np.ndarray,
    components: np.ndarray | None,
    component: int,
    tint: np.ndarray,
    bbox: list[int],
    row: np.ndarray,
    col: np.ndarray,
    mine: np.ndarray,  # (M,) indices of the instance's points
    removed: np.ndarray,
) -> np.ndarray:
    """The image around the instance: its mask component tinted in its class colour, its
    points dotted."""
    height, width = image.shape[:2]
    u0, v0 = max(bbox[0] - CROP_PAD_PX, 0), max(bbox[1] - CROP_PAD_PX, 0)
    u1, v1 = min(bbox[2] + CROP_PAD_PX, width - 1), min(bbox[3] + CROP_PAD_PX, height - 1)
    crop = image[v0 : v1 + 1, u0 : u1 + 1].astype(np.float32)
    if components is not None and component >= 0:
        on = components[v0 : v1 + 1, u0 : u1 + 1] == component
        crop[on] = 0.5 * crop[on] + 0.5 * tint.astype(np.float32)
    crop = crop.astype(np.uint8)
    dots = mine[row[mine] >= 0]
    colours = np.where(removed[dots, None], IMAGE_RGB[True], IMAGE_RGB[False]).astype(np.uint8)
    crop[row[dots] - v0, col[dots] - u0] = colours
    return crop


def class_colour(name: str) -> np.ndarray:
    """The overlay colour of a clutter class (white for the groups without a mask)."""
    if name in CLUTTER_CLASSES:
        return CLUTTER_COLORS[CLUTTER_CLASSES.index(name) + 1]
    return np.array((255, 255, 255), dtype=np.uint8)


def top_view(xyz: np.ndarray, mine: np.ndarray, removed: np.ndarray) -> np.ndarray:
    """A top view of the instance (`mine`: its point indices) and its surroundings, for
    instances outside the image."""
    own = xyz[mine, :2]
    centre = (own.min(axis=0) + own.max(axis=0)) / 2
    half = max(float(np.ptp(own, axis=0).max()) / 2 + 2.0, 4.0)
    scale = TOP_VIEW_PX / (2 * half)
    picture = np.zeros((TOP_VIEW_PX, TOP_VIEW_PX, 3), dtype=np.uint8)

    def pixels(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u = ((points[:, 0] - centre[0] + half) * scale).astype(np.int64)
        v = ((centre[1] + half - points[:, 1]) * scale).astype(np.int64)  # north up
        inside = (u >= 0) & (u < TOP_VIEW_PX) & (v >= 0) & (v < TOP_VIEW_PX)
        return v[inside], u[inside], inside

    v, u, _ = pixels(xyz[:, :2])
    picture[v, u] = 100
    v, u, inside = pixels(own)
    colours = np.where(removed[mine][inside, None], TOP_RGB[True], TOP_RGB[False])
    for dv in (-1, 0, 1):  # 3 x 3 dots: a few points must still show
        for du in (-1, 0, 1):
            picture[np.clip(v + dv, 0, TOP_VIEW_PX - 1), np.clip(u + du, 0, TOP_VIEW_PX - 1)] = (
                colours
            )
    return picture


def write_png(path: Path, rgb: np.ndarray) -> None:
    """`rgb` as a PNG file (OpenCV writes BGR)."""
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"could not encode the mask image {path}")
    path.write_bytes(png.tobytes())
