"""A phantom run from survey to output folder: the pipeline, the contract's files, the report."""

from __future__ import annotations

import time
from pathlib import Path

from app.core.progress import Progress
from app.core.sensors import SensorKind
from app.io.survey import Survey
from app.pipelines.outputs import write_report
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.evaluation.classification_metrics import metrics_from_counts
from app.pipelines.phantom.model import SHIPPED, read_card
from app.pipelines.phantom.outputs import write_confusion_plots
from app.pipelines.phantom.pipeline import PhantomPipeline
from app.pipelines.phantom.tiled import TILE_LENGTH, run_phantom_tiled
from app.pipelines.sensor_models import ModelChoice, choose_model
from app.pipelines.tiling import TileMap, in_process, tiles_report


def run_phantom_to_folder(
    survey: Survey,
    out: Path,
    config: PhantomConfig | None = None,
    model_path: Path | None = None,
    dense: bool = True,
    refine: bool = True,
    baselines: bool = False,
    progress: Progress | None = None,
    sensor: SensorKind | None = None,
    model: ModelChoice | None = None,
    tile_length: float = TILE_LENGTH,
    map_tiles: TileMap = in_process,
) -> dict:
    """`model` as a job chose it; else `model_path` forced by hand; else the shipped model of
    the survey's sensor kind (`sensor` declared, else detected): `sensor_models`. The survey
    runs tile by tile (`tiled`): `map_tiles` may spread the tiles over a cluster, and tiles an
    earlier attempt in `out` finished are kept."""
    started = time.perf_counter()
    config = (config or PhantomConfig()).model_copy(update={"refine": refine})
    if model is None:
        model = choose_model("phantom", SHIPPED, survey, read_card, model_path, sensor)
    pipeline = PhantomPipeline(config, model.path, dense)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    run = run_phantom_tiled(
        pipeline, survey, out, tile_length, progress=progress, map_tiles=map_tiles,
        baselines=baselines,
    )  # fmt: skip
    report: dict = {
        "pipeline": "phantom",
        "survey": {"name": survey.name, "format": survey.format, "source": str(survey.source)},
        "config": config.model_dump(),
        "model": {
            "path": str(pipeline.model_path),
            "created": pipeline.card.get("created"),
            "validation_f1": pipeline.card.get("validation", {}).get("macro", {}).get("f1"),
            **model.report(),
        },
        "path": "dense" if dense else "per-window",
        "tiles": tiles_report(run.index.layout, run.tiles_run, run.worker_peak_mb),
        "counts": {"frames": len(survey.frames), **run.counts},
        "timings": dict(run.timings),  # summed over the tiles
        "files": dict(run.files),
    }
    if run.metric_counts is not None:  # SemanticKITTI ids (simulator, SemanticKITTI)
        report["metrics"] = metrics_from_counts(run.metric_counts)
        report["files"].update(write_confusion_plots(out, report["metrics"]))
    report["timings"]["total"] = round(time.perf_counter() - started, 3)
    write_report(out, report)
    return report
