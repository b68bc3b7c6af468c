"""Evaluation plots drawn with OpenCV only: a confusion-matrix heat map and per-class bars.

`confusion_image` / `bar_image` return BGR uint8 images; `confusion_png` / `bar_png` write them
atomically (to ``<name>.partial.png`` first, then `os.replace`), so a reader never sees a
half-written PNG under the final name.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_AA = cv2.LINE_AA
_WHITE = np.array([255.0, 255.0, 255.0])
_DARK_BLUE = np.array([107.0, 48.0, 8.0])  # BGR of #08306b, the dark end of "Blues"
_BLACK = (0, 0, 0)
_GRID = (200, 200, 200)
_BAR = (180, 119, 31)  # BGR of #1f77b4

_TITLE = (0.7, 2)  # font scale, thickness
_LABEL = (0.5, 1)
_CELL_MAIN = (0.55, 1)
_CELL_SMALL = (0.42, 1)

NORMALIZE_MODES = ("row", "column", "all", "none")


def _size(text: str, style: tuple[float, int]) -> tuple[int, int]:
    (w, h), baseline = cv2.getTextSize(text, _FONT, style[0], style[1])
    return w, h + baseline


def _put(
    img: np.ndarray,
    text: str,
    cx: float,
    cy: float,
    style: tuple[float, int],
    color: tuple[int, int, int] = _BLACK,
    align: str = "center",
) -> None:
    """Write `text` vertically centred on cy; `align` says where cx is: center, right or left."""
    (w, h), _ = cv2.getTextSize(text, _FONT, style[0], style[1])
    x = {"center": cx - w / 2, "right": cx - w, "left": cx}[align]
    y = cy + h / 2
    cv2.putText(img, text, (round(x), round(y)), _FONT, style[0], color, style[1], _AA)


def _put_vertical(
    img: np.ndarray, text: str, cx: float, cy: float, style: tuple[float, int]
) -> None:
    """Write `text` rotated 90 degrees counter-clockwise (reading upwards), centred on cx, cy."""
    w, h = _size(text, style)
    patch = np.full((h + 6, w + 6, 3), 255, np.uint8)
    _put(patch, text, patch.shape[1] / 2, patch.shape[0] / 2, style)
    patch = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
    ph, pw = patch.shape[:2]
    x0 = max(0, round(cx - pw / 2))
    y0 = max(0, round(cy - ph / 2))
    region = img[y0 : y0 + ph, x0 : x0 + pw]
    np.minimum(region, patch[: region.shape[0], : region.shape[1]], out=region)


def _shade(t: float) -> tuple[int, int, int]:
    t = float(np.clip(t, 0.0, 1.0))
    color = _WHITE * (1.0 - t) + _DARK_BLUE * t
    return tuple(int(round(c)) for c in color)


def _normalised(confusion: np.ndarray, normalize: str | None) -> tuple[np.ndarray, np.ndarray]:
    """(shade in [0, 1], percentage shown or NaN where undefined) per cell."""
    counts = confusion.astype(np.float64)
    mode = "none" if normalize is None else normalize
    if mode not in NORMALIZE_MODES:
        raise ValueError(f"normalize must be one of {NORMALIZE_MODES} or None, got {normalize!r}")
    if mode == "row":
        denominator = np.broadcast_to(counts.sum(axis=1, keepdims=True), counts.shape)
    elif mode == "column":
        denominator = np.broadcast_to(counts.sum(axis=0, keepdims=True), counts.shape)
    else:
        denominator = np.full(counts.shape, counts.sum())
    fraction = np.full(counts.shape, np.nan)
    np.divide(counts, denominator, out=fraction, where=denominator > 0)
    if mode == "none":
        peak = counts.max() if counts.size else 0.0
        shade = counts / peak if peak > 0 else np.zeros(counts.shape)
    else:
        shade = np.nan_to_num(fraction, nan=0.0)
    return shade, 100.0 * fraction


def confusion_image(
    confusion: np.ndarray,
    names: Sequence[str],
    title: str,
    normalize: str | None = "row",
) -> np.ndarray:
    """BGR heat map: rows = reference, columns = predicted, each cell its percentage and count.

    `normalize`: "row" (share of the reference class, the default), "column" (share of the
    prediction), "all" (share of all samples) or "none"/None (shade by count, text = share of all).
    """
    confusion = np.asarray(confusion)
    names = [str(name) for name in names]
    if confusion.ndim != 2 or confusion.shape[0] != confusion.shape[1]:
        raise ValueError(f"confusion must be a square (C, C) matrix, got shape {confusion.shape}")
    if len(names) != confusion.shape[0]:
        raise ValueError(f"{len(names)} names for a {confusion.shape[0]}-class confusion matrix")
    n = len(names)
    shade, percent = _normalised(confusion, normalize)
    counts = confusion.astype(np.int64)
    percent_text = [[("-" if np.isnan(p) else f"{p:.1f}%") for p in row] for row in percent]
    count_text = [[f"{c:,}" for c in row] for row in counts]

    widest = max(
        [_size(name, _LABEL)[0] for name in names]
        + [_size(t, _CELL_MAIN)[0] for row in percent_text for t in row]
        + [_size(t, _CELL_SMALL)[0] for row in count_text for t in row]
        + [0]
    )
    cell_w = max(84, widest + 24)
    cell_h = 56
    caption_h = _size("reference", _LABEL)[1]
    row_name_w = max([_size(name, _LABEL)[0] for name in names] + [0])
    left = 12 + caption_h + 14 + row_name_w + 12
    title_w, title_h = _size(title, _TITLE)
    top = 14 + title_h + 14 + caption_h + 10 + caption_h + 12
    legend_w = 110
    grid_w, grid_h = n * cell_w, n * cell_h
    width = max(left + grid_w + legend_w, title_w + 40)
    height = top + grid_h + 20
    img = np.full((height, width, 3), 255, np.uint8)

    _put(img, title, width / 2, 14 + title_h / 2, _TITLE)
    caption_y = 14 + title_h + 14 + caption_h / 2
    _put(img, "predicted", left + grid_w / 2, caption_y, _LABEL)
    _put_vertical(img, "reference", 12 + caption_h / 2, top + grid_h / 2, _LABEL)
    names_y = top - 12 - caption_h / 2
    for j, name in enumerate(names):
        _put(img, name, left + (j + 0.5) * cell_w, names_y, _LABEL)
    for i, name in enumerate(names):
        _put(img, name, left - 12, top + (i + 0.5) * cell_h, _LABEL, align="right")

    for i in range(n):
        for j in range(n):
            x0, y0 = left + j * cell_w, top + i * cell_h
            t = float(shade[i, j])
            cv2.rectangle(img, (x0, y0), (x0 + cell_w, y0 + cell_h), _shade(t), cv2.FILLED)
            cv2.rectangle(img, (x0, y0), (x0 + cell_w, y0 + cell_h), _GRID, 1)
            ink = (255, 255, 255) if t > 0.5 else _BLACK
            cx = x0 + cell_w / 2
            _put(img, percent_text[i][j], cx, y0 + cell_h * 0.36, _CELL_MAIN, ink)
            _put(img, count_text[i][j], cx, y0 + cell_h * 0.74, _CELL_SMALL, ink)
    cv2.rectangle(img, (left, top), (left + grid_w, top + grid_h), (90, 90, 90), 1)

    # colour scale: 100 % at the top, 0 % at the bottom
    bar_x0, bar_x1 = left + grid_w + 18, left + grid_w + 36
    ramp = np.linspace(1.0, 0.0, max(grid_h, 2))[:, None]
    colours = (_WHITE * (1.0 - ramp) + _DARK_BLUE * ramp).round().astype(np.uint8)
    img[top : top + grid_h, bar_x0:bar_x1] = colours[:grid_h, None, :]
    cv2.rectangle(img, (bar_x0, top), (bar_x1, top + grid_h), (90, 90, 90), 1)
    top_label = "max" if normalize in (None, "none") else "100%"
    _put(img, top_label, bar_x1 + 6, top + 6, _CELL_SMALL, align="left")
    _put(img, "0", bar_x1 + 6, top + grid_h - 6, _CELL_SMALL, align="left")
    return img


def _nice_step(span: float, ticks: int = 5) -> float:
    raw = span / ticks
    magnitude = 10.0 ** math.floor(math.log10(raw))
    for factor in (1.0, 2.0, 2.5, 5.0, 10.0):
        if raw <= factor * magnitude:
            return factor * magnitude
    return 10.0 * magnitude


def _tick_text(value: float, step: float) -> str:
    decimals = next((d for d in range(7) if abs(round(step, d) - step) <= 1e-9 * step), 6)
    return f"{value:.{decimals}f}"


def bar_image(values: Mapping[str, float], title: str, ylabel: str) -> np.ndarray:
    """BGR bar chart, one bar per key, its value written above it; NaN values show "n/a"."""
    names = [str(name) for name in values]
    heights = np.array([float(v) for v in values.values()], dtype=np.float64)
    finite = heights[np.isfinite(heights)]
    lo = min(0.0, float(finite.min())) if finite.size else 0.0
    hi = max(0.0, float(finite.max())) if finite.size else 1.0
    if hi <= lo:
        hi = lo + 1.0
    step = _nice_step(hi - lo)
    lo = math.floor(lo / step + 1e-9) * step
    hi = math.ceil(hi / step - 1e-9) * step
    ticks = np.arange(lo, hi + step / 2, step)
    tick_labels = [_tick_text(t, step) for t in ticks]

    slot_w = max([64] + [_size(name, _LABEL)[0] + 16 for name in names])
    plot_h = 320
    caption_h = _size(ylabel, _LABEL)[1]
    tick_w = max(_size(t, _CELL_SMALL)[0] for t in tick_labels)
    left = 12 + caption_h + 12 + tick_w + 10
    title_w, title_h = _size(title, _TITLE)
    top = 14 + title_h + 30
    bottom = 16 + _size("Ag", _LABEL)[1] + 14
    plot_w = max(1, len(names)) * slot_w
    width = max(left + plot_w + 20, title_w + 40)
    height = top + plot_h + bottom
    img = np.full((height, width, 3), 255, np.uint8)

    def y_of(v: float) -> int:
        return round(top + plot_h * (hi - v) / (hi - lo))

    _put(img, title, width / 2, 14 + title_h / 2, _TITLE)
    _put_vertical(img, ylabel, 12 + caption_h / 2, top + plot_h / 2, _LABEL)
    for t, label in zip(ticks, tick_labels, strict=True):
        y = y_of(float(t))
        cv2.line(img, (left, y), (left + plot_w, y), (225, 225, 225), 1)
        cv2.line(img, (left - 5, y), (left, y), _BLACK, 1)
        _put(img, label, left - 8, y, _CELL_SMALL, align="right")
    zero = y_of(0.0)
    for k, (name, v) in enumerate(zip(names, heights, strict=True)):
        x0 = left + k * slot_w + slot_w // 6
        x1 = left + (k + 1) * slot_w - slot_w // 6
        cx = (x0 + x1) / 2
        if np.isfinite(v):
            y = y_of(float(v))
            cv2.rectangle(img, (x0, min(y, zero)), (x1, max(y, zero)), _BAR, cv2.FILLED)
            label_y = min(y, zero) - 10 if v >= 0 else max(y, zero) + 10
            _put(img, f"{v:.1f}", cx, label_y, _CELL_SMALL)
        else:
            _put(img, "n/a", cx, zero - 10, _CELL_SMALL)
        _put(img, name, cx, top + plot_h + 16 + _size("Ag", _LABEL)[1] / 2, _LABEL)
    if not names:
        _put(img, "no data", left + plot_w / 2, top + plot_h / 2, _LABEL)
    cv2.line(img, (left, top), (left, top + plot_h), _BLACK, 1)
    cv2.line(img, (left, zero), (left + plot_w, zero), _BLACK, 1)
    return img


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write `image` as PNG atomically: `<stem>.partial.png` first, then `os.replace`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"{path}: OpenCV could not encode the image as PNG")
    partial = path.with_suffix(".partial.png")
    try:
        partial.write_bytes(encoded.tobytes())
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return path


def confusion_png(
    path: str | Path,
    confusion: np.ndarray,
    names: Sequence[str],
    title: str,
    normalize: str | None = "row",
) -> Path:
    """Write the heat map of `confusion_image` to `path` (PNG, atomic); returns the path."""
    return write_png(path, confusion_image(confusion, names, title, normalize))


def bar_png(path: str | Path, values: Mapping[str, float], title: str, ylabel: str) -> Path:
    """Write the bar chart of `bar_image` to `path` (PNG, atomic); returns the path."""
    return write_png(path, bar_image(values, title, ylabel))
