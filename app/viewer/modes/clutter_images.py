"""The camera pictures of the clutter review: the frame's photo with the instances' mask images
pasted on (once per frame), the points dotted over it by state with the selected instance boxed
(again after every decision), and one instance's mask image as a thumbnail."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from app.store.clutter_review import InstanceState
from app.viewer.modes.clutter_states import SELECTED_RGB, STATE_RGB

IMAGE_WIDTH = 640  # px: the camera image as the GUI shows it (downscaled, sent as JPEG)
CROP_PAD_PX = 16  # the run pads each mask image by this around its instance's bbox


def blank_image() -> np.ndarray:
    """What the camera image shows when the frame has none."""
    return np.zeros((8, IMAGE_WIDTH, 3), np.uint8)


def masked_photo(photo: np.ndarray, states: Sequence[InstanceState]) -> tuple[np.ndarray, float]:
    """(the frame's camera image downscaled, with each instance's mask image pasted where
    it differs from the photo, i.e. the tinted mask; the scale), once per frame: decisions
    change only the dots drawn over it."""
    canvas = photo.copy()
    height, width = photo.shape[:2]
    for s in states:  # one paste per instance, not per point
        if s.bbox is None or not s.mask_path or not Path(s.mask_path).is_file():
            continue
        crop = cv2.imread(s.mask_path, cv2.IMREAD_COLOR)
        if crop is None:
            continue
        crop = cv2.cvtColor(crop, cv2.COLOR_BGR2RGB)
        u0, v0 = max(s.bbox[0] - CROP_PAD_PX, 0), max(s.bbox[1] - CROP_PAD_PX, 0)
        h = min(crop.shape[0], height - v0)
        w = min(crop.shape[1], width - u0)
        region = canvas[v0 : v0 + h, u0 : u0 + w]
        tinted = (crop[:h, :w] != photo[v0 : v0 + h, u0 : u0 + w]).any(axis=2)
        region[tinted] = crop[:h, :w][tinted]
    scale = IMAGE_WIDTH / width
    size = (IMAGE_WIDTH, max(int(round(height * scale)), 1))
    return cv2.resize(canvas, size, interpolation=cv2.INTER_AREA), scale


def overlay(
    photo: tuple[np.ndarray, float],
    pixels: tuple[np.ndarray, np.ndarray],
    owner: np.ndarray,
    state: np.ndarray,
    selected: InstanceState | None,
) -> np.ndarray:
    """The masked camera image (`masked_photo`) with the instances' points (`owner` >= 0, at
    their `pixels`, row / col, -1 outside) dotted by state and the `selected` instance boxed."""
    base, scale = photo
    small = base.copy()
    row, col = pixels
    dots = np.flatnonzero((owner >= 0) & (row >= 0))
    r = np.minimum((row[dots] * scale).astype(np.int64), small.shape[0] - 1)
    c = np.minimum((col[dots] * scale).astype(np.int64), small.shape[1] - 1)
    small[r, c] = STATE_RGB[state[dots]]
    if selected is not None and selected.bbox is not None:
        u0, v0, u1, v1 = (int(round(v * scale)) for v in selected.bbox)
        cv2.rectangle(small, (u0 - 2, v0 - 2), (u1 + 2, v1 + 2), SELECTED_RGB.tolist(), 1)
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
