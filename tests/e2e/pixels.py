"""Colours in a browser screenshot: the viewer draws in WebGL, so what a user sees (a preview,
a highlight box) is checked by counting pixels of its colour on the canvas."""

from __future__ import annotations

import io
from collections.abc import Callable

import numpy as np
from PIL import Image


def canvas_pixels(page) -> np.ndarray:
    """(h, w, 3) uint8 screenshot of the viewer's canvas."""
    png = page.locator("canvas").first.screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def count_pixels(page, predicate: Callable[[np.ndarray], np.ndarray]) -> int:
    return int(predicate(canvas_pixels(page).astype(np.int32)).sum())


def is_selection_green(rgb: np.ndarray) -> np.ndarray:
    """The pillar selection preview (40, 215, 60), shaded or not: no pillar class is green."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return (g > 120) & (g > 2 * r) & (g > 2 * b)


def is_target_red(rgb: np.ndarray) -> np.ndarray:
    """The review target outline (220, 20, 60), lit or not: not the magenta of phantom
    pillars (225, 20, 140) nor any orange."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return (r > 110) & (r > 3 * g) & (r > 2 * b)


def is_selected_magenta(rgb: np.ndarray) -> np.ndarray:
    """The clutter mode's selected instance (255, 0, 255): red and blue high, green low."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return (r > 150) & (b > 150) & (g < 80)


def is_hover_yellow(rgb: np.ndarray) -> np.ndarray:
    """viser's outline of a clickable mesh under the pointer (0xfbff00 at 0.8 opacity, drawn
    as about (234, 232, 135) on the software renderer): red and green high, blue well below."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return (r > 200) & (g > 200) & (b < 170) & (r - b > 70)
