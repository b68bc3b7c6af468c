"""Files of a phantom run besides labels and report: the cleaned map and the removed points as
LAZ (pillar class in `mmsclean_label`, ASPRS codes, source frame and index), the pillar grid
with the CNN's probabilities, and confusion-matrix plots when there is a reference."""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np

from app.io.asprs import PHANTOM_LABEL_TO_ASPRS, to_asprs
from app.io.las import write_laz
from app.pipelines.phantom.network import CLASS_NAMES
from app.pipelines.phantom.pipeline import PhantomResult
from app.pipelines.phantom.point_labels import kept


def write_maps(out: Path, result: PhantomResult) -> dict[str, str]:
    amap, labels = result.map, result.point_labels
    keep = kept(labels)
    frame, index = amap.source_frame, amap.source_index
    written = {}
    for name, sel in (("cleaned.laz", keep), ("removed.laz", ~keep)):
        if not sel.any():
            continue
        write_laz(
            Path(out) / name,
            amap.xyz[sel],
            mmsclean_label=labels[sel],
            classification=to_asprs(labels[sel], PHANTOM_LABEL_TO_ASPRS),
            source_frame=frame[sel],
            source_index=index[sel],
            creation_date=datetime.date.today(),
        )
        written[name.removesuffix(".laz")] = name
    pm = result.pillar_map
    np.savez_compressed(
        Path(out) / "pillars.npz",
        pillars=pm.pillars,
        probabilities=result.probabilities,
        classified=result.classified,
        raw_labels=result.raw_labels,
        labels=result.pillar_labels,
        cell_size=pm.config.cell_size,
    )
    written["pillars"] = "pillars.npz"
    return written


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
