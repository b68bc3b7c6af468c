"""Fixtures of the clutter tests: the pretrained segmentation weights."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from app.pipelines.clutter.segmenter import WEIGHTS_FILE


@pytest.fixture(scope="session")
def weights_dir() -> Path:
    """The folder named by MMSCLEAN_WEIGHTS_DIR holding the ESPNetv2 weights; skip without."""
    value = os.environ.get("MMSCLEAN_WEIGHTS_DIR")
    if not value:
        pytest.skip("MMSCLEAN_WEIGHTS_DIR is not set (pretrained ESPNetv2 weights)")
    path = Path(value).resolve()
    if not (path / WEIGHTS_FILE).is_file():
        pytest.skip(f"MMSCLEAN_WEIGHTS_DIR={value} holds no {WEIGHTS_FILE}")
    return path
