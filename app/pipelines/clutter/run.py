"""A clutter run from survey to output folder, tile by tile (`tiled`): the contract's files
(labels, cleaned and removed LAZ), overlays and the report; and the maps and scores of given
per-frame decisions (the web app's recompute, `mmsclean evaluate`)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from app.core.progress import Progress
from app.io.survey import Survey
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.evaluation.removal_metrics import (
    metrics_from_counts,
    survey_removal_counts,
)
from app.pipelines.clutter.pipeline import ClutterPipeline
from app.pipelines.clutter.segmenter import CachedSegmenter, overlay_png
from app.pipelines.clutter.tiled import (
    TILE_LENGTH,
    ClutterTiledRun,
    cached_segmentation,
    run_clutter_tiled,
)
from app.pipelines.outputs import write_report
from app.pipelines.tiling import TileMap, in_process, tiles_report


def run_clutter_to_folder(
    survey: Survey, out: Path, config: ClutterConfig | None = None, **options
) -> dict:
    """The run's report (the options: `run_clutter_report`)."""
    return run_clutter_report(survey, out, config, **options)[0]


def run_clutter_report(
    survey: Survey,
    out: Path,
    config: ClutterConfig | None = None,
    overlays: int = 0,
    progress: Progress | None = None,
    tile_length: float = TILE_LENGTH,
    map_tiles: TileMap = in_process,
    review: bool = False,
    cache_dir: Path | None = None,
    weights_dir: Path | None = None,
) -> tuple[dict, ClutterTiledRun]:
    """The survey tile by tile (`tiled`) into `out`, then the report; returns it and the run
    (with `review`, the run's review rows for the web app's store). `map_tiles` may spread the
    tiles over a cluster; tiles an earlier attempt in `out` finished are kept. The segmentation
    network and its cache come from the settings unless named."""
    started = time.perf_counter()
    config = config or ClutterConfig()
    out = Path(out)
    run = run_clutter_tiled(
        config, survey, out, tile_length, progress=progress, map_tiles=map_tiles, review=review,
        cache_dir=cache_dir, weights_dir=weights_dir,
    )  # fmt: skip
    files = dict(run.files)
    camera = ClutterPipeline(config).camera(survey)
    segmenter = None
    if camera is not None:
        cached = cached_segmentation(cache_dir, weights_dir, config.image_gamma)
        segmenter = {"name": cached.name, **run.segmentation}
        if overlays:
            files.update(_write_overlays(out, survey, camera.name, cached, overlays))
    report: dict = {
        "pipeline": "clutter",
        "survey": {"name": survey.name, "format": survey.format, "source": str(survey.source)},
        "config": config.model_dump(),
        "segmenter": segmenter,
        "tiles": tiles_report(run.tiles.layout, run.tiles_run, run.worker_peak_mb),
        "counts": dict(run.counts),
        "timings": dict(run.timings),  # summed over the tiles
        "files": files,
    }
    if run.metric_counts is not None:
        report["metrics"] = metrics_from_counts(run.metric_counts)
    report["timings"]["total"] = round(time.perf_counter() - started, 3)
    write_report(out, report)
    return report, run


def reference_metrics(
    survey: Survey, removed: list[np.ndarray], in_view: list[np.ndarray]
) -> dict | None:
    """The paper's removal metrics of per-frame removed flags against the survey's reference
    labels, frame by frame; None when it has none."""
    frames = np.arange(len(survey.frames))
    counts = survey_removal_counts(survey, frames, removed, in_view)
    return None if counts is None else metrics_from_counts(counts)


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
