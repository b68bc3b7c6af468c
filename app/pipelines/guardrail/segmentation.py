"""The guardrail pipeline up to the classifier's input, shared by running and training:
points -> road removal -> connected components -> 0.5 m slices -> camera crops -> crop
embeddings and geometric features."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.core.progress import Progress, Stopwatch, no_progress
from app.io.survey import Survey
from app.pipelines.guardrail.classifier import EMBEDDING, CropEncoder
from app.pipelines.guardrail.components import Components, connected_components
from app.pipelines.guardrail.crops import slice_crops
from app.pipelines.guardrail.features import slice_features
from app.pipelines.guardrail.road import RoadRemoval, road_removal
from app.pipelines.guardrail.scan_points import ScanPoints, load_scan_points
from app.pipelines.guardrail.slices import SliceSet, cut_slices


@dataclass
class SliceStage:
    points: ScanPoints
    trajectory: np.ndarray  # (M, 3) sensor positions in drive order
    road: RoadRemoval
    components: Components
    slices: SliceSet
    geometry: np.ndarray  # (K, G) float32
    geometry_names: list[str]
    embedding: np.ndarray  # (K, 1280) float32, zeros where no image shows the slice whole
    has_crop: np.ndarray  # (K,) bool
    crop_frames: np.ndarray  # (K,) int64 frame of the crop, -1 without
    crop_boxes: np.ndarray  # (K, 4) int64 (u0, v0, u1, v1), -1 without
    timings: dict[str, float]


# where the slice steps lie in an untiled run's progress (they report 0-1 within themselves;
# the classifier follows at 0.7, the reconstruction at 0.8)
SLICE_STEPS = {
    "points": (0.0, 0.1),
    "road removal": (0.1, 0.2),
    "components": (0.2, 0.3),
    "crops": (0.3, 0.4),
    "crop embeddings": (0.4, 0.7),
}


def prepare_slices(
    survey: Survey,
    encoder: CropEncoder | None,
    spacing: float = 0.5,
    progress: Progress | None = None,
    min_slice_points: int = 5,
) -> SliceStage:
    """Everything the classifier needs; `encoder=None` skips the images (geometry only)."""
    report = progress or no_progress
    clock = Stopwatch()
    with clock("load"):
        report("points", 0.0)
        points = load_scan_points(survey)
        trajectory = survey.poses()[:, :3, 3]
    stage = slice_stage(survey, points, trajectory, encoder, spacing, report, min_slice_points)
    stage.timings = {**clock.rounded(), **stage.timings}
    return stage


def slice_stage(
    survey: Survey,
    points: ScanPoints,
    trajectory: np.ndarray,
    encoder: CropEncoder | None,
    spacing: float = 0.5,
    progress: Progress | None = None,
    min_slice_points: int = 5,
    crop_only: Callable[[SliceSet], np.ndarray] | None = None,
    origin: np.ndarray | None = None,
) -> SliceStage:
    """`prepare_slices` on points already loaded (a tile's: `trajectory` is the whole drive's,
    so stations are the survey's). `crop_only` picks the slices worth a camera crop (default
    all): a tile crops the slices whose labels it keeps, not its halo's. `origin` anchors the
    ground cells and voxels (default: the points' mean; a tile passes the survey's mean)."""
    report = progress or no_progress
    clock = Stopwatch()
    with clock("road"):
        report("road removal", 0.0)
        road = road_removal(points.xyz, trajectory, origin=origin)
    with clock("components"):
        report("components", 0.0)
        origin = points.xyz.mean(axis=0) if origin is None and len(points) else origin
        components = connected_components(
            points, road.keep, above_ground=road.above_ground, origin=origin
        )
    with clock("slices"):
        slices = cut_slices(points.xyz, components.label, trajectory, spacing,
                            min_points=min_slice_points)  # fmt: skip
        geometry, names = slice_features(points.xyz, slices, above_ground=road.above_ground)
    k = len(slices)
    embedding = np.zeros((k, EMBEDDING), dtype=np.float32)
    has_crop = np.zeros(k, dtype=bool)
    crop_frames = np.full(k, -1, dtype=np.int64)
    crop_boxes = np.full((k, 4), -1, dtype=np.int64)
    if encoder is not None and survey.cameras and k:
        with clock("crops"):
            report("crops", 0.0)
            wanted = None if crop_only is None else crop_only(slices)
            crops = slice_crops(survey, slices, points.xyz, slices=wanted)
        with clock("embeddings"):
            report("crop embeddings", 0.0)
            if crops:
                which = np.array([c.slice for c in crops], dtype=np.int64)
                total = len(crops)

                def embedded(n: int) -> None:
                    report(f"crop embeddings ({n:,} of {total:,})", n / total)

                embedding[which] = encoder.embed([c.image for c in crops], embedded)
                has_crop[which] = True
                crop_frames[which] = [c.frame for c in crops]
                crop_boxes[which] = [c.box for c in crops]
    return SliceStage(
        points, trajectory, road, components, slices, geometry, names, embedding, has_crop,
        crop_frames, crop_boxes, clock.rounded(),
    )  # fmt: skip


def save_slice_features(path: Path, stage: SliceStage, slices: np.ndarray | None = None) -> Path:
    """Per slice (`slices`: these only): its key (component, slice index), the classifier's
    inputs (image embedding as float16, geometric features) and whether a camera crop showed
    it: what retraining the classifier on reviewed slices reads."""
    picked = np.arange(len(stage.slices)) if slices is None else np.asarray(slices, np.int64)
    partial = path.with_suffix(".partial.npz")
    np.savez(
        partial,
        component=stage.slices.component[picked],
        slice_index=stage.slices.station_index[picked],
        embedding=stage.embedding[picked].astype(np.float16),
        geometry=stage.geometry[picked].astype(np.float32),
        geometry_names=np.array(stage.geometry_names),
        has_crop=stage.has_crop[picked],
    )
    partial.replace(path)
    return path


FEATURE_COLUMNS = ("embedding", "geometry", "has_crop")  # per slice, in `save_slice_features`


def index_slice_features(path: Path, parts: list[Path], components: list[np.ndarray]) -> Path:
    """An index of feature files (`save_slice_features`, e.g. a tiled run's tiles, beside it):
    every slice's key, with `components` (per part, the run's component number of each of its
    slices), while the features stay in the parts (`read_slice_features`). Small: per slice."""
    path = Path(path)
    slice_index, names = [], np.array([], dtype=str)
    for part in parts:
        with np.load(part) as data:
            slice_index.append(data["slice_index"])
            names = data["geometry_names"]
    partial = path.with_suffix(".partial.npz")
    np.savez(
        partial, geometry_names=names,
        parts=np.array([str(Path(p).relative_to(path.parent)) for p in parts]),
        part_slices=np.array([len(k) for k in slice_index], dtype=np.int64),
        component=np.concatenate(components) if components else np.zeros(0, np.int64),
        slice_index=np.concatenate(slice_index) if slice_index else np.zeros(0, np.int64),
    )  # fmt: skip
    partial.replace(path)
    return path


def slice_feature_keys(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(component, slice index) of every slice a features file (or index) holds, in its order."""
    with np.load(path) as data:
        return data["component"], data["slice_index"]


def read_slice_features(path: Path, rows: np.ndarray) -> dict[str, np.ndarray]:
    """The features of the slices at `rows` (in `slice_feature_keys`' order), in that order, and
    the geometric features' names; from an index, only the parts holding them are read."""
    rows = np.asarray(rows, dtype=np.int64)
    with np.load(path) as data:
        if "parts" not in data.files:
            return {"geometry_names": data["geometry_names"],
                    **{c: data[c][rows] for c in FEATURE_COLUMNS}}  # fmt: skip
        names, parts, sizes = data["geometry_names"], data["parts"], data["part_slices"]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    part_of = np.searchsorted(starts, rows, side="right") - 1
    out: dict[str, np.ndarray] = {"geometry_names": names}
    # no rows: the first part still gives each column's shape and type
    for k in np.unique(part_of) if len(rows) else range(min(len(parts), 1)):
        at = np.flatnonzero(part_of == k)
        with np.load(Path(path).parent / str(parts[k])) as data:
            for c in FEATURE_COLUMNS:
                values = data[c][rows[at] - starts[k]]
                if c not in out:
                    out[c] = np.zeros((len(rows), *values.shape[1:]), dtype=values.dtype)
                out[c][at] = values
    for c in FEATURE_COLUMNS:  # an index of no parts
        out.setdefault(c, np.zeros(0))
    return out
