"""Confusion-matrix plots of a phantom run with a reference (the labels, maps and pillar grid
are written tile by tile: `tile_outputs`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.pipelines.phantom.network import CLASS_NAMES


def write_confusion_plots(out: Path, metrics: dict) -> dict[str, str]:
    from app.metrics.plots import confusion_png

    written = {}
    for key in ("pillar", "point"):
        if key in metrics:
            name = f"confusion_{key}.png"
            confusion = np.asarray(metrics[key]["confusion"])
            confusion_png(Path(out) / name, confusion, list(CLASS_NAMES), f"phantom: {key} level")
            written[f"confusion_{key}"] = name
    return written
