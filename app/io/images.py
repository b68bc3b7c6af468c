"""Camera image files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from app.core.errors import InputError


def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB; a missing or undecodable file is an InputError naming it."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(path, "is missing or not a readable image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of a PNG from its header, without decoding; other formats are decoded."""
    with open(path, "rb") as fh:
        head = fh.read(24)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 24:
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    h, w = read_rgb(path).shape[:2]
    return w, h
