"""Confusion heat map and bar chart PNGs: written atomically, readable, with real content."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from app.metrics.plots import bar_png, confusion_image, confusion_png

NAMES = ["short object", "high object", "phantom", "ground"]
CM = np.array(
    [
        [926, 31, 40, 3],
        [30, 932, 35, 3],
        [70, 30, 885, 15],
        [2, 6, 6, 986],
    ]
)


def _assert_png(path: Path) -> np.ndarray:
    assert path.is_file()
    assert path.stat().st_size > 5_000
    assert not list(path.parent.glob("*.partial*"))
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None
    assert img.ndim == 3 and img.shape[0] > 150 and img.shape[1] > 200
    assert img.std() > 10  # not a blank canvas
    return img


def test_confusion_png_written_and_readable(tmp_path: Path) -> None:
    out = confusion_png(tmp_path / "plots" / "confusion.png", CM, NAMES, "phantom: test set")
    assert out == tmp_path / "plots" / "confusion.png"
    img = _assert_png(out)
    # the heat map uses the dark end of the colour scale (diagonal cells above 50 %)
    dark_blue = (img[..., 0] > 90) & (img[..., 2] < 30)
    assert dark_blue.sum() > 1_000


@pytest.mark.parametrize("normalize", ["row", "column", "all", "none", None])
def test_confusion_image_normalisations(normalize: str | None) -> None:
    img = confusion_image(CM, NAMES, "t", normalize=normalize)
    assert img.dtype == np.uint8 and img.shape[2] == 3


def test_confusion_image_empty_rows_and_bad_input() -> None:
    img = confusion_image(np.zeros((3, 3), int), ["a", "b", "c"], "empty")
    assert img.shape[0] > 100
    with pytest.raises(ValueError, match="normalize"):
        confusion_image(CM, NAMES, "t", normalize="rows")
    with pytest.raises(ValueError, match="names"):
        confusion_image(CM, NAMES[:3], "t")


def test_shading_follows_the_counts() -> None:
    diag = confusion_image(np.diag([10, 10]), ["a", "b"], "t")
    off = confusion_image(np.array([[0, 10], [10, 0]]), ["a", "b"], "t")
    assert diag.shape == off.shape
    # same layout, shading moved: the images differ, and both hold as much ink
    assert np.abs(diag.astype(int) - off.astype(int)).sum() > 0
    assert abs(int(diag.sum()) - int(off.sum())) < 0.02 * int(diag.sum())


def test_bar_png_written_and_readable(tmp_path: Path) -> None:
    values = {"short object": 89.5, "high object": 95.6, "phantom": 89.3, "ground": 99.2}
    out = bar_png(tmp_path / "f1.png", values, "F-measure per class", "F [%]")
    img = _assert_png(out)
    bar_blue = (np.abs(img[..., 0].astype(int) - 180) < 10) & (img[..., 2] < 50)
    assert bar_blue.sum() > 5_000


def test_bar_png_negative_nan_and_empty(tmp_path: Path) -> None:
    _assert_png(bar_png(tmp_path / "a.png", {"a": -3.0, "b": float("nan"), "c": 12.0}, "t", "y"))
    out = bar_png(tmp_path / "b.png", {}, "nothing", "y")
    assert cv2.imread(str(out)) is not None


def test_overwrite_replaces_existing_file(tmp_path: Path) -> None:
    path = tmp_path / "cm.png"
    path.write_bytes(b"old")
    confusion_png(path, CM, NAMES, "new")
    _assert_png(path)
