"""`mmsclean run clutter | phantom | guardrail`: a pipeline on a survey, into a run folder."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli.common import (
    FormatOption,
    SensorOption,
    config_from_options,
    console,
    err_console,
    sensor_kind,
    stage_progress,
)

run_app = typer.Typer(help="Run a pipeline on a survey (labels, cleaned map, report).")

SurveyFolder = Annotated[Path, typer.Argument(help="survey folder (frames with poses and images)")]
OutFolder = Annotated[Path, typer.Option("--out", "-o", help="output folder")]

# what each `run` command prints: (summary, scores against the reference labels), as templates
REPORT_LINES = {
    "clutter": (
        "{out}: {frames} frames, {points:,} points, {removed_points:,} removed ({mode} mode), "
        "map {map_points:,} points ({total:.1f} s)",
        "full map, moving objects: SA {full[dynamic][scores][SA]:.2f} "
        "DA {full[dynamic][scores][DA]:.2f} AA {full[dynamic][scores][AA]:.2f}; camera view, "
        "movable objects: overall accuracy {in_view[clutter][error_matrix][overall_accuracy]:.2f}, "
        "clutter omission {in_view[clutter][error_matrix][clutter_omission]:.2f}, "
        "map commission {in_view[clutter][error_matrix][map_commission]:.3f}",
    ),
    "phantom": (
        "{out}: {points:,} points, {phantom_points:,} phantom points removed, {pillars:,} pillars "
        "({total:.1f} s)",
        "pillar level: overall F {pillar[macro][f1]:.1f}, "
        "phantom F {pillar[classes][phantom][f1]:.1f}",
    ),
    "guardrail": (
        "{out}: {points:,} points, {slices:,} slices, {guardrail_slices:,} guardrail slices, "
        "{guardrails} guardrails ({total:.1f} s)",
        "slices vs {reference}: precision {slice[precision]:.1f}, recall {slice[recall]:.1f}, "
        "F {slice[f1]:.1f}",
    ),
}


def cluster_settings(scheduler: str | None):
    """The settings with `--scheduler` in place of MMSCLEAN_DASK_SCHEDULER (checked alike)."""
    from pydantic import ValidationError

    from app.core.errors import ConfigError
    from app.core.settings import Settings, get_settings

    settings = get_settings()
    if scheduler is None:
        return settings
    try:
        return Settings.model_validate({**settings.model_dump(), "dask_scheduler": scheduler})
    except ValidationError:
        raise ConfigError(
            "--scheduler",
            f"{scheduler!r} is not a Dask scheduler address (tcp://host:8786 or tls://host:8786)",
        ) from None


TileLengthOption = Annotated[
    float, typer.Option(min=20.0, max=1000.0, help="metres of trajectory per tile")
]
SchedulerOption = Annotated[
    str | None,
    typer.Option(
        help="Dask scheduler that runs the tiles (tcp://host:8786; default "
        "MMSCLEAN_DASK_SCHEDULER, else MMSCLEAN_WORKERS local processes)"
    ),
]


@run_app.command("clutter")
def run_clutter(
    source: SurveyFolder,
    fmt: FormatOption,
    out: OutFolder,
    mode: Annotated[
        str, typer.Option(help="clutter: every movable object (the paper); dynamic: moved ones")
    ] = "clutter",
    padding: Annotated[int, typer.Option(help="mask buffer in pixels (the paper: 30)")] = 30,
    expansion: Annotated[
        str, typer.Option(help="cluster: 3D expansion (mmsclean); pad: padded masks (the paper)")
    ] = "cluster",
    camera: Annotated[bool, typer.Option(help="use the camera masks")] = True,
    image_gamma: Annotated[
        float | None,
        typer.Option(
            help="gamma on the camera image before segmentation (0.2-2, below 1 "
            "lifts dark tones; default ClutterConfig's)"
        ),
    ] = None,
    free_space: Annotated[bool, typer.Option(help="use DUFOMap free-space evidence")] = True,
    tracking: Annotated[bool, typer.Option(help="link objects across frames")] = True,
    voxel_dedup: Annotated[
        float | None, typer.Option(help="metres: keep one point per voxel in the cleaned map")
    ] = None,
    dufomap_resolution: Annotated[
        float, typer.Option(help="metres: voxel edge of the free-space map (0.02-5)")
    ] = 0.1,
    threads: Annotated[
        int, typer.Option(help="threads per tile worker, 0 = the cores shared among them")
    ] = 0,
    overlays: Annotated[int, typer.Option(help="write mask overlays of the first N frames")] = 0,
    tile_length: TileLengthOption = 100.0,
    scheduler: SchedulerOption = None,
) -> None:
    """Clutter removal (Lee et al.): camera masks, 3D expansion, free space, tracking, tile by
    tile. Rerun into the same folder, it keeps the tiles an interrupted run finished."""
    from app.io import open_survey
    from app.jobs.cluster import close_clients, shared_threads, tile_map
    from app.pipelines.clutter.config import ClutterConfig
    from app.pipelines.clutter.run import run_clutter_to_folder

    settings = cluster_settings(scheduler)
    config = config_from_options(
        ClutterConfig,
        {"mask_padding_px": "padding"},
        mode=mode,
        mask_padding_px=padding,
        expansion=expansion,
        use_camera=camera,
        **({} if image_gamma is None else {"image_gamma": image_gamma}),
        use_free_space=free_space,
        use_tracking=tracking,
        voxel_dedup=voxel_dedup,
        dufomap_resolution=dufomap_resolution,
        threads=threads or shared_threads(settings),
    )
    survey = open_survey(source, fmt)
    try:
        with stage_progress("clutter") as progress:
            report = run_clutter_to_folder(
                survey, out, config=config, overlays=overlays, progress=progress,
                tile_length=tile_length, map_tiles=tile_map(settings),
            )  # fmt: skip
    finally:
        close_clients()
    print_report("clutter", report, out=out, mode=mode)


@run_app.command("phantom")
def run_phantom(
    source: Annotated[Path, typer.Argument(help="survey folder or point-cloud file")],
    fmt: FormatOption,
    out: OutFolder,
    model: Annotated[
        Path | None,
        typer.Option(help="checkpoint (default: the shipped one for the survey's sensor kind)"),
    ] = None,
    windows: Annotated[
        bool, typer.Option("--windows", help="per-window reference path instead of dense")
    ] = False,
    refine: Annotated[bool, typer.Option(help="Algorithm 1 neighbourhood vote")] = True,
    baselines: Annotated[
        bool, typer.Option(help="also score the paper's two baselines (needs reference labels)")
    ] = False,
    sensor: SensorOption = None,
    tile_length: TileLengthOption = 100.0,
    scheduler: SchedulerOption = None,
) -> None:
    """Phantom removal (Nagy & Benedek): pillar 3D CNN on the accumulated map, tile by tile.
    Rerun into the same folder, it keeps the tiles an interrupted run finished."""
    from app.io import open_survey
    from app.jobs.cluster import close_clients, tile_map
    from app.pipelines.phantom.run import run_phantom_to_folder

    survey = open_survey(source, fmt)
    try:
        with stage_progress("phantom") as progress:
            report = run_phantom_to_folder(
                survey,
                out,
                model_path=model,
                dense=not windows,
                refine=refine,
                baselines=baselines,
                progress=progress,
                sensor=sensor_kind(sensor),
                tile_length=tile_length,
                map_tiles=tile_map(cluster_settings(scheduler)),
            )
    finally:
        close_clients()
    print_report("phantom", report, out=out)


@run_app.command("guardrail")
def run_guardrail(
    source: SurveyFolder,
    fmt: FormatOption,
    out: OutFolder,
    model: Annotated[
        Path | None,
        typer.Option(help="classifier checkpoint (default: shipped, for the sensor kind)"),
    ] = None,
    head: Annotated[
        str | None,
        typer.Option(
            help="classifier inputs: image+geometry, image (the paper), geometry "
            "(default: the model's, from its card)"
        ),
    ] = None,
    reconstruct: Annotated[bool, typer.Option(help="model the guardrails as meshes")] = True,
    sensor: SensorOption = None,
    tile_length: TileLengthOption = 100.0,
    scheduler: SchedulerOption = None,
) -> None:
    """Guardrails (Matsumoto et al.): slices, camera-crop classifier, poles, unit shapes, meshes.
    Tile by tile, each guardrail one model whatever the tiles; rerun into the same folder, it
    keeps the tiles an interrupted run finished."""
    from app.io import open_survey
    from app.jobs.cluster import close_clients, tile_map
    from app.pipelines.guardrail.config import GuardrailConfig
    from app.pipelines.guardrail.run import run_guardrail_to_folder

    config = config_from_options(GuardrailConfig, head=head, reconstruct=reconstruct)
    survey = open_survey(source, fmt)
    try:
        with stage_progress("guardrail") as progress:
            report = run_guardrail_to_folder(
                survey, out, config, model, progress=progress, sensor=sensor_kind(sensor),
                tile_length=tile_length, map_tiles=tile_map(cluster_settings(scheduler)),
            )  # fmt: skip
    finally:
        close_clients()
    print_report("guardrail", report, out=out)


def print_report(pipeline: str, report: dict, **values: object) -> None:
    """A run's one-line summary (its counts, seconds and `values`), then its scores when the
    survey had reference labels to score against."""
    summary, scores = REPORT_LINES[pipeline]
    warning = report.get("model", {}).get("warning")
    if warning:
        err_console.print(f"[yellow]warning:[/yellow] {warning}", soft_wrap=True)
    console.print(summary.format(**report["counts"], total=report["timings"]["total"], **values))
    if "metrics" in report:
        console.print(scores.format(**report["metrics"]))
