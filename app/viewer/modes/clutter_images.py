"""The camera pictures of the clutter review: the frame's photo with the instances' mask images
pasted on (once per frame, at the width the panel shows), the points dotted over it by state
with the selected instance highlighted (its points, its mask's outline and its box, magenta as
in the 3D view; again after every decision or selection), and one instance's mask image as a
thumbnail."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from app.store.clutter_review import InstanceState
from app.viewer.modes.clutter_states import SELECTED_RGB, STATE_RGB

IMAGE_WIDTH = 640  # px: the camera image as the GUI shows it (downscaled, sent as JPEG)
# the image's width for each "Panel width" of the mode: sharp when the panel is large
IMAGE_WIDTHS = {"Small": IMAGE_WIDTH, "Medium": IMAGE_WIDTH, "Large": 1280}
CROP_PAD_PX = 16  # the run pads each mask image by this around its instance's bbox
SELECTED_DOT = 1  # px: the selected instance's points are drawn (2 * this + 1) px wide


def blank_image() -> np.ndarray:
    """What the camera image shows when the frame has none."""
    return np.zeros((8, IMAGE_WIDTH, 3), np.uint8)


def _tinted(photo: np.ndarray, s: InstanceState) -> tuple[int, int, np.ndarray, np.ndarray] | None:
    """(u0, v0, the instance's mask image cropped to the photo, where it differs from the
    photo: the tinted mask and its dots) at full resolution; None without a mask image."""
    if s.bbox is None or not s.mask_path or not Path(s.mask_path).is_file():
        return None
    crop = cv2.imread(s.mask_path, cv2.IMREAD_COLOR)
    if crop is None:
        return None
    crop = cv2.cvtColor(crop, cv2.COLOR_BGR2RGB)
    height, width = photo.shape[:2]
    u0, v0 = max(s.bbox[0] - CROP_PAD_PX, 0), max(s.bbox[1] - CROP_PAD_PX, 0)
    h = max(min(crop.shape[0], height - v0), 0)
    w = max(min(crop.shape[1], width - u0), 0)
    crop = crop[:h, :w]
    return u0, v0, crop, (crop != photo[v0 : v0 + h, u0 : u0 + w]).any(axis=2)


def masked_photo(
    photo: np.ndarray, states: Sequence[InstanceState], image_width: int = IMAGE_WIDTH
) -> tuple[np.ndarray, float]:
    """(the frame's camera image downscaled to `image_width`, with each instance's mask image
    pasted where it differs from the photo, i.e. the tinted mask; the scale), once per frame:
    decisions change only the dots drawn over it."""
    canvas = photo.copy()
    height, width = photo.shape[:2]
    for s in states:  # one paste per instance, not per point
        found = _tinted(photo, s)
        if found is None:
            continue
        u0, v0, crop, tinted = found
        region = canvas[v0 : v0 + crop.shape[0], u0 : u0 + crop.shape[1]]
        region[tinted] = crop[tinted]
    scale = image_width / width
    size = (image_width, max(int(round(height * scale)), 1))
    return cv2.resize(canvas, size, interpolation=cv2.INTER_AREA), scale


def mask_outline(photo: np.ndarray, s: InstanceState, scale: float) -> list[np.ndarray]:
    """The outline of the instance's tinted mask (its dots opened away) as contours in the
    downscaled image's pixels; none without a mask image."""
    found = _tinted(photo, s)
    if found is None or not found[3].any():
        return []
    u0, v0, _, tinted = found
    mask = cv2.morphologyEx(tinted.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    offset = np.array([u0, v0])
    return [np.round((c + offset) * scale).astype(np.int32) for c in contours]


def pixel_bbox(pixels: tuple[np.ndarray, np.ndarray], points: np.ndarray) -> list[int] | None:
    """[u0, v0, u1, v1] around the `points` (indices) that project into the image (`pixels`:
    row / col per point, -1 outside); None when none does."""
    row, col = pixels
    points = np.asarray(points, dtype=np.int64)
    seen = points[row[points] >= 0]
    if not len(seen):
        return None
    r, c = row[seen], col[seen]
    return [int(c.min()), int(r.min()), int(c.max()), int(r.max())]


def overlay(
    photo: tuple[np.ndarray, float],
    pixels: tuple[np.ndarray, np.ndarray],
    owner: np.ndarray,
    state: np.ndarray,
    selected: InstanceState | None,
    raw_photo: np.ndarray | None = None,
) -> np.ndarray:
    """The masked camera image (`masked_photo`) with the instances' points (`owner` >= 0, at
    their `pixels`, row / col, -1 outside) dotted by state and the `selected` instance
    highlighted: its points drawn larger in the selection colour, its mask outlined (from the
    full-size `raw_photo`, when given) and a box around its points (or its mask's box)."""
    base, scale = photo
    small = base.copy()
    row, col = pixels
    dots = np.flatnonzero((owner >= 0) & (row >= 0))
    r = np.minimum((row[dots] * scale).astype(np.int64), small.shape[0] - 1)
    c = np.minimum((col[dots] * scale).astype(np.int64), small.shape[1] - 1)
    small[r, c] = STATE_RGB[state[dots]]
    if selected is None:
        return small
    colour = SELECTED_RGB.tolist()
    if raw_photo is not None:
        cv2.drawContours(small, mask_outline(raw_photo, selected, scale), -1, colour, 1)
    mine = owner[dots] == selected.instance_index
    rr, cc = r[mine], c[mine]
    for dr in range(-SELECTED_DOT, SELECTED_DOT + 1):  # a loop over offsets, not points
        for dc in range(-SELECTED_DOT, SELECTED_DOT + 1):
            small[
                np.clip(rr + dr, 0, small.shape[0] - 1), np.clip(cc + dc, 0, small.shape[1] - 1)
            ] = SELECTED_RGB
    box = pixel_bbox(pixels, dots[mine]) or selected.bbox
    if box is not None:
        u0, v0, u1, v1 = (int(round(v * scale)) for v in box)
        cv2.rectangle(small, (u0 - 3, v0 - 3), (u1 + 3, v1 + 3), colour, 1)
    return small


def mask_thumbnail(mask_path: str | None) -> np.ndarray | None:
    """An instance's mask image (RGB), at most half the camera image wide; None without one."""
    image = None
    if mask_path and Path(mask_path).is_file():
        image = cv2.imread(mask_path, cv2.IMREAD_COLOR)
    if image is None:
        return None
    image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.shape[1] > IMAGE_WIDTH // 2:
        scale = (IMAGE_WIDTH // 2) / image.shape[1]
        size = (IMAGE_WIDTH // 2, max(int(round(image.shape[0] * scale)), 1))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return image
