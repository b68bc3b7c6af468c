"""What every pipeline run writes (DESIGN.md's command-line contract): OUT/labels/<frame>.npy
(one uint8 per raw input point, file order) and OUT/report.json. Files are written whole or
not at all (temporary name, then rename)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np


def write_frame_labels(out: Path, labels: dict[str, np.ndarray]) -> None:
    folder = Path(out) / "labels"
    folder.mkdir(parents=True, exist_ok=True)
    for frame_id, values in labels.items():
        target = folder / f"{frame_id}.npy"
        partial = folder / f"{frame_id}.partial.npy"
        np.save(partial, np.asarray(values, dtype=np.uint8))
        os.replace(partial, target)


def write_report(out: Path, report: dict) -> Path:
    return write_json(Path(out) / "report.json", report)


def write_json(path: Path, data: dict) -> Path:
    """`data` as indented JSON at `path` (numpy values made plain), whole or not at all."""
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(data, indent=1, sort_keys=True, default=_plain) + "\n")
    os.replace(partial, path)
    return path


def _plain(value: object) -> object:
    """numpy scalars and arrays in reports become plain JSON values."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
