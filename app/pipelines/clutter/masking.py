"""Projection and masking (the paper's step 3): which LiDAR points fall on which clutter mask.

Points are projected with the survey's calibration; points outside the image (behind the
camera, beside it) are untouched by this step. The paper pads every mask by a 30 px buffer to
catch the laser "halo" around car bodies; `padded` is that decision, `mask_class` the class under
the unpadded mask (what the 3D expansion starts from).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from app.geometry.projection import pixel_indices, project
from app.io.survey import Camera


@dataclass
class FrameMasking:
    """Per point of one frame: where it lands in the image and which mask covers it."""

    in_view: np.ndarray  # (N,) bool: projects into the image in front of the camera
    depth: np.ndarray  # (N,) float64 camera depth (nan / negative outside the view)
    rows: np.ndarray  # (V,) int64 pixel row of each in-view point (point order)
    cols: np.ndarray  # (V,) int64 pixel column
    mask_class: np.ndarray  # (N,) uint8 clutter class under the unpadded mask, 0 = none
    padded: np.ndarray  # (N,) bool: under a mask dilated by the padding (the paper's removal)


def pad_mask(mask: np.ndarray, padding_px: int) -> np.ndarray:
    """The boolean mask grown by `padding_px` pixels in every direction (a disc)."""
    if padding_px <= 0:
        return mask.astype(bool)
    size = 2 * padding_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def mask_points(
    xyz: np.ndarray, camera: Camera, class_map: np.ndarray, padding_px: int
) -> FrameMasking:
    """Look up the class map (H, W uint8, 0 = not clutter) under each sensor-frame point."""
    height, width = class_map.shape
    if (width, height) != (camera.width, camera.height):
        raise ValueError(
            f"class map is {width}x{height}, camera {camera.name} is {camera.width}x{camera.height}"
        )
    proj = project(xyz, camera.P, camera.T_cam_sensor, width, height)
    rows, cols = pixel_indices(proj)
    n = len(xyz)
    mask_class = np.zeros(n, dtype=np.uint8)
    mask_class[proj.in_image] = class_map[rows, cols]
    padded = np.zeros(n, dtype=bool)
    padded[proj.in_image] = pad_mask(class_map > 0, padding_px)[rows, cols]
    return FrameMasking(proj.in_image, proj.depth, rows, cols, mask_class, padded)
