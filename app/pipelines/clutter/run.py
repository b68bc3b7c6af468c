"""A clutter run from survey to output folder: segmentation (cached), the pipeline, the
contract's files (labels, cleaned and removed LAZ), overlays and the report."""

from __future__ import annotations

import datetime
import time
from pathlib import Path

import numpy as np

from app.core.progress import Progress
from app.io.accumulate import AccumulatedMap
from app.io.asprs import REMOVED_CLUTTER_ASPRS
from app.io.las import write_laz
from app.io.survey import Frame, Survey
from app.pipelines.clutter.accumulate import kept_and_removed
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.pipeline import ClassMaps, ClutterPipeline, ClutterResult
from app.pipelines.clutter.segmenter import CachedSegmenter, Segmenter, overlay_png
from app.pipelines.outputs import write_frame_labels, write_report


def segmented_class_maps(
    survey: Survey,
    camera: str,
    segmenter: Segmenter | None = None,
    progress: Progress | None = None,
    cache_dir: Path | None = None,
) -> tuple[ClassMaps, CachedSegmenter]:
    """Segment every frame's image of `camera` in batches (cached per image file, under
    `cache_dir`, default the settings' cache), then hand the pipeline a per-frame lookup."""
    if segmenter is None:
        from app.pipelines.clutter.segmenter import ESPNetv2Segmenter

        segmenter = ESPNetv2Segmenter()
    cached = CachedSegmenter(segmenter, cache_dir)
    paths = [f.image_paths[camera] for f in survey.frames if camera in f.image_paths]
    step = max(cached.chunk, 1)
    for start in range(0, len(paths), step):
        if progress:
            progress("segmentation", start / max(len(paths), 1))
        cached.segment_files(paths[start : start + step])

    def class_map(frame: Frame) -> np.ndarray:
        return cached.segment_files([frame.image_paths[camera]])[0]

    return class_map, cached


def run_clutter(
    survey: Survey,
    config: ClutterConfig | None = None,
    segmenter: Segmenter | None = None,
    progress: Progress | None = None,
    cache_dir: Path | None = None,
) -> tuple[ClutterResult, CachedSegmenter | None, float]:
    """The pipeline with its segmentation; returns the result, the cache and the network time."""
    pipeline = ClutterPipeline(config or ClutterConfig())
    camera = pipeline.camera(survey)
    cached = None
    started = time.perf_counter()
    if camera is not None:
        pipeline.class_maps, cached = segmented_class_maps(
            survey, camera.name, segmenter, progress, cache_dir
        )
    segmentation_s = time.perf_counter() - started
    return pipeline.run(survey, progress), cached, segmentation_s


def run_clutter_to_folder(
    survey: Survey,
    out: Path,
    config: ClutterConfig | None = None,
    segmenter: Segmenter | None = None,
    overlays: int = 0,
    progress: Progress | None = None,
) -> dict:
    started = time.perf_counter()
    config = config or ClutterConfig()
    result, cached, segmentation_s = run_clutter(survey, config, segmenter, progress)
    return write_clutter_outputs(
        survey, out, config, result, cached, segmentation_s, overlays, started
    )


def write_clutter_outputs(
    survey: Survey,
    out: Path,
    config: ClutterConfig,
    result: ClutterResult,
    cached: CachedSegmenter | None,
    segmentation_s: float,
    overlays: int = 0,
    started: float | None = None,
) -> dict:
    """The contract's files of a finished run (labels, cleaned and removed LAZ, overlays,
    report.json); the web app's job calls it between the run and its review ingestion."""
    started = time.perf_counter() if started is None else started
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_frame_labels(out, result.frame_labels())
    t0 = time.perf_counter()
    kept, removed = kept_and_removed(survey, result.removed, config.voxel_dedup)
    result.timings["accumulation"] = round(time.perf_counter() - t0, 3)
    files = write_maps(out, kept, removed)
    camera = ClutterPipeline(config).camera(survey)
    if overlays and cached is not None and camera is not None:
        files.update(_write_overlays(out, survey, camera.name, cached, overlays))
    timings = {"segmentation_with_cache": round(segmentation_s, 3), **result.timings}
    report: dict = {
        "pipeline": "clutter",
        "survey": {"name": survey.name, "format": survey.format, "source": str(survey.source)},
        "config": config.model_dump(),
        "segmenter": None if cached is None else {"name": cached.name, "cache_hits": cached.hits},
        "counts": {
            "frames": len(result.frame_ids),
            "points": int(sum(len(r) for r in result.removed)),
            "points_in_view": int(sum(int(v.sum()) for v in result.in_view)),
            "removed_points": int(sum(int(r.sum()) for r in result.removed)),
            "map_points": int(len(kept.xyz)),
            "tracks": 0 if result.tracks is None else len(result.tracks.tracks),
        },
        "timings": timings,
        "files": files,
    }
    metrics = reference_metrics(survey, result.removed, result.in_view)
    if metrics is not None:
        report["metrics"] = metrics
    report["timings"]["total"] = round(time.perf_counter() - started, 3)
    write_report(out, report)
    return report


def reference_metrics(
    survey: Survey, removed: list[np.ndarray], in_view: list[np.ndarray]
) -> dict | None:
    """The paper's removal metrics of per-frame removed flags against the survey's reference
    labels; None when it has none."""
    if "semantic" not in survey.reference_label_kinds:
        return None
    from app.pipelines.clutter.evaluation.removal_metrics import removal_metrics

    references = [f.reference_labels() for f in survey.frames]
    semantic = np.concatenate([r["semantic"] for r in references])
    moving = None
    if "moving" in survey.reference_label_kinds:  # the simulator's per-point flag
        moving = np.concatenate([r["moving"] for r in references])
    return removal_metrics(semantic, np.concatenate(removed), np.concatenate(in_view), moving)


def write_maps(out: Path, kept: AccumulatedMap, removed: AccumulatedMap) -> dict[str, str]:
    """cleaned.laz and removed.laz in `out`; returns {name: file name}."""
    written = {}
    for name, world, label in (("cleaned.laz", kept, 0), ("removed.laz", removed, 1)):
        n = len(world.xyz)
        write_laz(
            out / name,
            world.xyz,
            mmsclean_label=np.full(n, label, dtype=np.uint8),
            classification=np.full(n, REMOVED_CLUTTER_ASPRS if label else 1, dtype=np.uint8),
            source_frame=world.source_frame,
            source_index=world.source_index,
            intensity=None if world.intensity is None else _reflectance(world.intensity),
            creation_date=datetime.date.today(),
        )
        written[name.removesuffix(".laz")] = name
    return written


def _reflectance(values: np.ndarray) -> np.ndarray:
    """Reflectance 0..1 to the LAS 16-bit range; values already above 1 are kept as they are."""
    values = np.asarray(values, dtype=np.float64)
    return values * 65535.0 if values.size and values.max() <= 1.0 else values


def _write_overlays(
    out: Path, survey: Survey, camera: str, cached: CachedSegmenter, count: int
) -> dict[str, str]:
    """The first `count` frames' images with their clutter masks, as PNGs under overlays/."""
    from app.io.images import read_rgb

    written = {}
    folder = out / "overlays"
    folder.mkdir(exist_ok=True)
    for frame in list(survey.frames)[:count]:
        if camera not in frame.image_paths:
            continue
        path = frame.image_paths[camera]
        class_map = cached.lookup(path)
        if class_map is None:
            continue
        overlay_png(read_rgb(path), class_map, folder / f"{frame.frame_id}.png")
        written[f"overlay_{frame.frame_id}"] = f"overlays/{frame.frame_id}.png"
    return written
