"""`mmsclean evaluate`: a run's labels scored against the survey's reference labels, as tables."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from app.cli.common import FormatOption, console


def evaluate(
    pipeline: Annotated[str, typer.Argument(help="clutter, phantom or guardrail")],
    run: Annotated[Path, typer.Argument(help="run output folder (labels/<frame>.npy inside)")],
    source: Annotated[Path, typer.Argument(help="the survey the labels are for")],
    fmt: FormatOption,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="also write the metrics to this JSON file")
    ] = None,
) -> None:
    """Score a run's labels (any tool's, in the run contract) against the reference labels."""
    from app.io import open_survey
    from app.pipelines.evaluation import PIPELINES, evaluate_labels, read_frame_labels
    from app.pipelines.outputs import write_json

    if pipeline not in PIPELINES:
        from app.core.errors import ConfigError

        raise ConfigError("PIPELINE", f"must be one of {', '.join(PIPELINES)} (got {pipeline!r})")
    survey = open_survey(source, fmt)
    metrics = evaluate_labels(survey, pipeline, read_frame_labels(run, survey, pipeline))
    if json_out is not None:
        write_json(json_out, {"pipeline": pipeline, "run": str(run), "metrics": metrics})
    for title, header, rows in metric_tables(pipeline, metrics):
        table = Table(title=title, title_justify="left")
        for name in header:
            table.add_column(name, justify="left" if name == header[0] else "right")
        for row in rows:
            table.add_row(*row)
        console.print(table)


def metric_tables(pipeline: str, metrics: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows) of the tables `evaluate` prints."""
    if pipeline == "clutter":
        rows = []
        for scope, label in (("in_view", "camera view"), ("full", "full map")):
            for kind, what in (("dynamic", "moving"), ("clutter", "movable")):
                e = metrics[scope][kind]["error_matrix"]
                d = metrics[scope][kind]["scores"]
                rows.append(
                    [f"{label}, {what}", f"{d['SA']:.2f}", f"{d['DA']:.2f}", f"{d['AA']:.2f}"]
                    + [f"{e['overall_accuracy']:.2f}", f"{e['clutter_omission']:.2f}"]
                    + [f"{e['clutter_commission']:.2f}", f"{e['map_commission']:.3f}"]
                )
        header = ["scope, reference", "SA", "DA", "AA", "OA", "clutter om.", "clutter com."]
        return [("clutter removal", [*header, "map com."], rows)]
    header = ["class", "precision", "recall", "F", "support"]
    if pipeline == "phantom":
        point = metrics["point"]
        rows = [
            [name] + [_score(v) for v in cls.values()]
            for name, cls in (*point["classes"].items(), ("overall", point["macro"]))
        ]
        detection = metrics["phantom_points"]
        found = [["phantom points"] + [_score(v) for v in detection.values()]]
        return [("phantom: points in the pillar layer", header, rows), ("", header, found)]
    point = metrics["point"]
    return [
        (f"guardrail points vs {metrics['reference']}", header,
         [["guardrail"] + [_score(v) for v in point.values()]]),
    ]  # fmt: skip


def _score(value: float | int) -> str:
    """A percentage with one decimal, a count as it is."""
    return f"{value:.1f}" if isinstance(value, float) else str(value)
