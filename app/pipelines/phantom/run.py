"""A phantom run from survey to output folder: the pipeline, the contract's files, the report."""

from __future__ import annotations

import time
from pathlib import Path

from app.core.labels import PillarClass
from app.core.progress import Progress
from app.core.sensors import SensorKind
from app.io.survey import Survey
from app.pipelines.outputs import write_frame_labels, write_report
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.model import SHIPPED, read_card
from app.pipelines.phantom.outputs import write_confusion_plots, write_maps
from app.pipelines.phantom.pipeline import PhantomPipeline
from app.pipelines.sensor_models import ModelChoice, choose_model


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
) -> dict:
    """`model` as a job chose it; else `model_path` forced by hand; else the shipped model of
    the survey's sensor kind (`sensor` declared, else detected): `sensor_models`."""
    started = time.perf_counter()
    config = (config or PhantomConfig()).model_copy(update={"refine": refine})
    if model is None:
        model = choose_model("phantom", SHIPPED, survey, read_card, model_path, sensor)
    pipeline = PhantomPipeline(config, model.path, dense)
    result = pipeline.run(survey, progress)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_frame_labels(out, result.frame_labels())
    files = write_maps(out, result)
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
        "counts": {
            "frames": len(result.map.frame_ids),
            "points": int(len(result.point_labels)),
            "points_in_layer": int(result.pillar_map.in_layer.sum()),
            "pillars": int(len(result.pillar_map.pillars)),
            "pillars_classified": int(result.classified.sum()),
            "pillars_per_class": {
                name.name.lower(): int((result.pillar_labels == name).sum()) for name in PillarClass
            },
            "phantom_points": int((result.point_labels == PillarClass.phantom).sum()),
        },
        "timings": dict(result.timings),
        "files": files,
    }
    if "semantic" in result.map.reference:  # SemanticKITTI ids (simulator, SemanticKITTI)
        from app.pipelines.phantom.evaluation.classification_metrics import evaluate

        flags = {}
        if baselines:
            from app.pipelines.phantom.evaluation.baselines import avg_distances, num_neighbors

            t0 = time.perf_counter()
            flags["num_neighbors"] = num_neighbors(result.map.xyz)
            flags["avg_distances"] = avg_distances(result.map.xyz)
            report["timings"]["baselines"] = round(time.perf_counter() - t0, 3)
        report["metrics"] = evaluate(result, flags)
        files.update(write_confusion_plots(out, report["metrics"]))
    report["timings"]["total"] = round(time.perf_counter() - started, 3)
    write_report(out, report)
    return report
