"""What every pipeline run writes (DESIGN.md's command-line contract): OUT/labels/<frame>.npy
(one uint8 per raw input point, file order) and OUT/report.json. Files are written whole or
not at all (temporary name, then rename)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np


def write_frame_labels(out: Path, labels: dict[str, np.ndarray]) -> None:
    (Path(out) / "labels").mkdir(parents=True, exist_ok=True)
    for frame_id, values in labels.items():
        target, partial = _label_paths(out, frame_id)
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


def _label_paths(out: Path, frame_id: str) -> tuple[Path, Path]:
    folder = Path(out) / "labels"
    return folder / f"{frame_id}.npy", folder / f"{frame_id}.partial.npy"


def start_frame_labels(out: Path, sizes: dict[str, int]) -> None:
    """Zeroed label files on disk for labels that arrive in parts (a tiled run's tiles): filled
    by `fill_frame_labels`, renamed to their names by `commit_frame_labels`. Nothing of them is
    held in memory."""
    for frame_id, size in sizes.items():
        partial = _label_paths(out, frame_id)[1]
        partial.parent.mkdir(parents=True, exist_ok=True)
        if not size:  # an empty file cannot be mapped
            np.save(partial, np.zeros(0, dtype=np.uint8))
            continue
        np.lib.format.open_memmap(partial, mode="w+", dtype=np.uint8, shape=(int(size),)).flush()


def fill_frame_labels(out: Path, frame_id: str, index: np.ndarray, values: np.ndarray) -> None:
    labels = np.lib.format.open_memmap(_label_paths(out, frame_id)[1], mode="r+")
    labels[index] = values
    labels.flush()
    del labels


def fill_labels_of_frames(
    out: Path, frame_ids: list[str], frame: np.ndarray, index: np.ndarray, values: np.ndarray
) -> None:
    """`fill_frame_labels` for points of many frames: point k is `index[k]` of frame
    `frame_ids[frame[k]]`."""
    if len(frame) == 0:
        return
    order = np.argsort(frame, kind="stable")
    frame, index, values = frame[order], index[order], values[order]
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    for a, b in zip(starts, np.r_[starts[1:], len(frame)], strict=True):
        fill_frame_labels(out, frame_ids[int(frame[a])], index[a:b], values[a:b])


def commit_frame_labels(out: Path, frame_ids: list[str]) -> None:
    for frame_id in frame_ids:
        target, partial = _label_paths(out, frame_id)
        os.replace(partial, target)
