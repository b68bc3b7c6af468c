"""`mmsclean info` and `mmsclean simulate`: read a survey's summary, or make a survey."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from app.cli.common import FormatOption, config_from_options, console, err_console


def info(
    source: Annotated[Path, typer.Argument(help="survey folder or point-cloud file")],
    fmt: FormatOption,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON instead of a table")] = False,
    check: Annotated[
        bool, typer.Option("--check", help="read every frame: validate data, world bounds")
    ] = False,
) -> None:
    """Summarise a survey: frames, points, time span, trajectory, cameras, reference labels."""
    from rich.progress import Progress

    from app.io import open_survey
    from app.io.summary import check_frames, summarize, summary_rows

    survey = open_survey(source, fmt)
    summary = summarize(survey)
    if check:
        with Progress(console=err_console, transient=True, disable=as_json) as bar:
            task = bar.add_task("reading frames", total=len(survey))
            summary = check_frames(survey, summary, lambda: bar.advance(task))
    if as_json:
        console.print_json(json.dumps(summary.as_dict()))
        return
    table = Table(show_header=False, box=None)
    table.add_column(no_wrap=True)
    table.add_column(overflow="fold")
    for key, value in summary_rows(summary):
        table.add_row(f"[bold]{key}[/bold]", value)
    console.print(table)


def simulate(
    out: Annotated[Path, typer.Option("--out", "-o", help="output folder (KITTI-raw-like)")],
    scene: Annotated[
        str,
        typer.Option(
            help="a street: urban, highway, mixed, interchange; or a situation clutter removal "
            "finds hard: receding, approaching, walkers, market, shadow, parked_rows"
        ),
    ] = "urban",
    length: Annotated[float, typer.Option(help="metres of street driven")] = 60.0,
    seed: Annotated[int, typer.Option(help="same seed, same bytes")] = 0,
    scanner: Annotated[str, typer.Option(help="hdl64 (frames) or profile (MLS map)")] = "hdl64",
    camera: Annotated[bool, typer.Option(help="render camera images and masks")] = True,
    pose_noise_m: Annotated[float, typer.Option(help="GNSS/INS position noise sigma")] = 0.0,
    pose_noise_deg: Annotated[float, typer.Option(help="GNSS/INS heading noise sigma")] = 0.0,
    write_map: Annotated[
        bool | None, typer.Option("--map/--no-map", help="write map.laz (default: profile)")
    ] = None,
    compressed: Annotated[
        bool, typer.Option(help="scans as LAZ (per-point time inside) instead of KITTI .bin")
    ] = False,
    drive_speed: Annotated[
        float | None, typer.Option(help="the survey vehicle's speed, m/s (default: the seed's)")
    ] = None,
    vegetation: Annotated[
        bool, typer.Option(help="town streets: hedges and bushes along the sidewalks")
    ] = False,
    overwrite: Annotated[bool, typer.Option(help="replace OUT if it exists")] = False,
) -> None:
    """Simulate a mobile-mapping survey with complete ground truth."""
    from rich.progress import Progress

    from app.simulate.survey import SimulationConfig
    from app.simulate.survey import simulate as run_simulation

    config = config_from_options(
        SimulationConfig,
        scene=scene,
        length=length,
        seed=seed,
        scanner=scanner,
        camera=camera,
        pose_noise_m=pose_noise_m,
        pose_noise_deg=pose_noise_deg,
        write_map=write_map,
        compressed=compressed,
        drive_speed=drive_speed,
        vegetation=vegetation,
    )
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task(f"simulating {config.scene} ({config.scanner})", total=None)
        summary = run_simulation(
            config,
            out,
            overwrite,
            lambda done, total: bar.update(task, completed=done, total=total),
        )
    console.print(
        f"{summary.out}: {summary.frames} frames, {summary.points:,} points, "
        f"{summary.moving_objects} moving objects, {summary.parked_vehicles} parked vehicles, "
        f"guardrails: {', '.join(summary.guardrails) or 'none'} "
        f"({summary.seconds:.1f} s, {summary.points_per_second:,.0f} points/s)"
    )
