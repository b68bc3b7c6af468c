"""The `mmsclean` command line.

Every user error (`MmscleanError`) ends in one line on stderr and a non-zero exit code, never a
traceback; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from app.core.errors import MmscleanError

cli = typer.Typer(
    name="mmsclean",
    help="Clean mobile-mapping point clouds: clutter and phantom removal, guardrail models.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)


def option_error(exc, renames: dict[str, str] | None = None) -> MmscleanError:
    """The first problem of a config's pydantic ValidationError, named by its command-line
    option (`field_name` -> `--field-name`, or as `renames` says) and the value given."""
    from app.core.errors import ConfigError

    first = exc.errors()[0]
    field = str(first["loc"][0])
    option = (renames or {}).get(field, field).replace("_", "-")
    return ConfigError(f"--{option}", f"{first['msg']} (got {first.get('input')!r})")


FormatOption = Annotated[
    str, typer.Option("--format", "-f", help="kitti-raw, semantickitti, las, ply, pcd, sim")
]


@cli.command()
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


@cli.command()
def simulate(
    out: Annotated[Path, typer.Option("--out", "-o", help="output folder (KITTI-raw-like)")],
    scene: Annotated[str, typer.Option(help="urban, highway or mixed")] = "urban",
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
    overwrite: Annotated[bool, typer.Option(help="replace OUT if it exists")] = False,
) -> None:
    """Simulate a mobile-mapping survey with complete ground truth."""
    from pydantic import ValidationError
    from rich.progress import Progress

    from app.simulate.survey import SimulationConfig
    from app.simulate.survey import simulate as run_simulation

    try:
        config = SimulationConfig(
            scene=scene,
            length=length,
            seed=seed,
            scanner=scanner,
            camera=camera,
            pose_noise_m=pose_noise_m,
            pose_noise_deg=pose_noise_deg,
            write_map=write_map,
            compressed=compressed,
        )
    except ValidationError as exc:
        raise option_error(exc) from None
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


run_app = typer.Typer(help="Run a pipeline on a survey (labels, cleaned map, report).")
cli.add_typer(run_app, name="run")
train_app = typer.Typer(help="Train a pipeline's model.")
cli.add_typer(train_app, name="train")


@run_app.command("clutter")
def run_clutter(
    source: Annotated[Path, typer.Argument(help="survey folder (frames with poses and images)")],
    fmt: FormatOption,
    out: Annotated[Path, typer.Option("--out", "-o", help="output folder")],
    mode: Annotated[
        str, typer.Option(help="clutter: every movable object (the paper); dynamic: moved ones")
    ] = "clutter",
    padding: Annotated[int, typer.Option(help="mask buffer in pixels (the paper: 30)")] = 30,
    expansion: Annotated[
        str, typer.Option(help="cluster: 3D expansion (mmsclean); pad: padded masks (the paper)")
    ] = "cluster",
    camera: Annotated[bool, typer.Option(help="use the camera masks")] = True,
    free_space: Annotated[bool, typer.Option(help="use DUFOMap free-space evidence")] = True,
    tracking: Annotated[bool, typer.Option(help="link objects across frames")] = True,
    voxel_dedup: Annotated[
        float | None, typer.Option(help="metres: keep one point per voxel in the cleaned map")
    ] = None,
    dufomap_resolution: Annotated[
        float, typer.Option(help="metres: voxel edge of the free-space map (0.02-5)")
    ] = 0.1,
    threads: Annotated[int, typer.Option(help="worker threads, 0 = all cores")] = 0,
    overlays: Annotated[int, typer.Option(help="write mask overlays of the first N frames")] = 0,
) -> None:
    """Clutter removal (Lee et al.): camera masks, 3D expansion, free space, tracking."""
    from pydantic import ValidationError
    from rich.progress import Progress

    from app.io import open_survey
    from app.pipelines.clutter.config import ClutterConfig
    from app.pipelines.clutter.run import run_clutter_to_folder

    try:
        config = ClutterConfig(
            mode=mode,
            mask_padding_px=padding,
            expansion=expansion,
            use_camera=camera,
            use_free_space=free_space,
            use_tracking=tracking,
            voxel_dedup=voxel_dedup,
            dufomap_resolution=dufomap_resolution,
            threads=threads,
        )
    except ValidationError as exc:
        raise option_error(exc, {"mask_padding_px": "padding"}) from None
    survey = open_survey(source, fmt)
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task("clutter", total=1.0)
        report = run_clutter_to_folder(
            survey,
            out,
            config,
            overlays=overlays,
            progress=lambda stage, f: bar.update(task, completed=f, description=stage),
        )
    counts = report["counts"]
    console.print(
        f"{out}: {counts['frames']} frames, {counts['points']:,} points, "
        f"{counts['removed_points']:,} removed ({mode} mode), map {counts['map_points']:,} "
        f"points ({report['timings']['total']:.1f} s)"
    )
    if "metrics" in report:
        full = report["metrics"]["full"]["dynamic"]["scores"]
        view = report["metrics"]["in_view"]["clutter"]["error_matrix"]
        console.print(
            f"full map, moving objects: SA {full['SA']:.2f} DA {full['DA']:.2f} AA "
            f"{full['AA']:.2f}; camera view, movable objects: overall accuracy "
            f"{view['overall_accuracy']:.2f}, clutter omission {view['clutter_omission']:.2f}, "
            f"map commission {view['map_commission']:.3f}"
        )


@run_app.command("phantom")
def run_phantom(
    source: Annotated[Path, typer.Argument(help="survey folder or point-cloud file")],
    fmt: FormatOption,
    out: Annotated[Path, typer.Option("--out", "-o", help="output folder")],
    model: Annotated[Path | None, typer.Option(help="checkpoint (default: shipped)")] = None,
    windows: Annotated[
        bool, typer.Option("--windows", help="per-window reference path instead of dense")
    ] = False,
    refine: Annotated[bool, typer.Option(help="Algorithm 1 neighbourhood vote")] = True,
    baselines: Annotated[
        bool, typer.Option(help="also score the paper's two baselines (needs reference labels)")
    ] = False,
) -> None:
    """Phantom removal (Nagy & Benedek): pillar 3D CNN on the accumulated map."""
    from rich.progress import Progress

    from app.io import open_survey
    from app.pipelines.phantom.run import run_phantom_to_folder

    survey = open_survey(source, fmt)
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task("phantom", total=1.0)
        report = run_phantom_to_folder(
            survey,
            out,
            model_path=model,
            dense=not windows,
            refine=refine,
            baselines=baselines,
            progress=lambda stage, f: bar.update(task, completed=f, description=stage),
        )
    console.print(
        f"{out}: {report['counts']['points']:,} points, {report['counts']['phantom_points']:,} "
        f"phantom points removed, {report['counts']['pillars']:,} pillars "
        f"({report['timings']['total']:.1f} s)"
    )
    if "metrics" in report:
        pillar = report["metrics"]["pillar"]
        console.print(
            f"pillar level: overall F {pillar['macro']['f1']:.1f}, phantom F "
            f"{pillar['classes']['phantom']['f1']:.1f}"
        )


@run_app.command("guardrail")
def run_guardrail(
    source: Annotated[Path, typer.Argument(help="survey folder (frames with poses and images)")],
    fmt: FormatOption,
    out: Annotated[Path, typer.Option("--out", "-o", help="output folder")],
    model: Annotated[
        Path | None, typer.Option(help="classifier checkpoint (default: shipped)")
    ] = None,
    head: Annotated[
        str, typer.Option(help="classifier inputs: image+geometry, image (the paper), geometry")
    ] = "image+geometry",
    reconstruct: Annotated[bool, typer.Option(help="model the guardrails as meshes")] = True,
) -> None:
    """Guardrails (Matsumoto et al.): slices, camera-crop classifier, poles, unit shapes, meshes."""
    from pydantic import ValidationError
    from rich.progress import Progress

    from app.io import open_survey
    from app.pipelines.guardrail.pipeline import GuardrailConfig
    from app.pipelines.guardrail.run import run_guardrail_to_folder

    try:
        config = GuardrailConfig(head=head, reconstruct=reconstruct)
    except ValidationError as exc:
        raise option_error(exc) from None
    survey = open_survey(source, fmt)
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task("guardrail", total=1.0)
        report = run_guardrail_to_folder(
            survey,
            out,
            config,
            model,
            progress=lambda stage, f: bar.update(task, completed=f, description=stage),
        )
    counts = report["counts"]
    console.print(
        f"{out}: {counts['points']:,} points, {counts['slices']:,} slices, "
        f"{counts['guardrail_slices']:,} guardrail slices, {counts['guardrails']} guardrails "
        f"({report['timings']['total']:.1f} s)"
    )
    if "metrics" in report:
        s = report["metrics"]["slice"]
        console.print(
            f"slices vs {report['metrics']['reference']}: precision {s['precision']:.1f}, "
            f"recall {s['recall']:.1f}, F {s['f1']:.1f}"
        )


@train_app.command("phantom")
def train_phantom(
    out: Annotated[Path, typer.Option("--out", "-o", help="checkpoint to write (.pt)")] = Path(
        "models/phantom/phantom_cnn_context.pt"
    ),
    sim_seeds: Annotated[
        str, typer.Option(help="simulator seeds: 101,102 or 101-110 (presets cycle)")
    ] = "101-110,114-200,204-250",
    sim_length: Annotated[float, typer.Option(help="metres per simulated survey")] = 200.0,
    semantickitti: Annotated[
        list[Path] | None, typer.Option(help="SemanticKITTI sequence folder (repeatable)")
    ] = None,
    per_class: Annotated[int, typer.Option(help="pillars per class (paper: 10,000)")] = 20_000,
    epochs: Annotated[int, typer.Option(help="training epochs")] = 10,
    folds_to_run: Annotated[int, typer.Option(help="folds of the 5-fold split to train")] = 1,
    seed: Annotated[int, typer.Option(help="sampling / initialisation seed")] = 0,
    context: Annotated[
        int, typer.Option(help="channels of the 6.2 m context branch (0: the paper's network)")
    ] = 16,
) -> None:
    """Train the phantom 3D CNN on simulated surveys and SemanticKITTI sequences."""
    from pydantic import ValidationError
    from rich.progress import Progress

    from app.core.errors import ConfigError
    from app.pipelines.phantom.train import TrainConfig, train_phantom_model

    seeds = _seed_list("--sim-seeds", sim_seeds)
    for folder in semantickitti or []:
        if not (folder / "velodyne").is_dir():
            raise ConfigError("--semantickitti", f"{folder} is not a SemanticKITTI sequence")
    try:
        config = TrainConfig(
            per_class=per_class,
            epochs=epochs,
            folds_to_run=folds_to_run,
            seed=seed,
            context=context,
        )
    except ValidationError as exc:
        raise option_error(exc) from None
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task("training", total=1.0)
        card = train_phantom_model(
            out,
            seeds,
            list(semantickitti or []),
            config,
            lambda stage, f: bar.update(task, completed=f, description=stage),
            sim_length=sim_length,
        )
    validation = card["validation"]
    per_class = ", ".join(f"{k} {c['f1']:.1f}" for k, c in validation["classes"].items())
    console.print(
        f"{out}: validation F per class: {per_class}; macro {validation['macro']['f1']:.1f}"
    )


@train_app.command("guardrail")
def train_guardrail(
    out: Annotated[Path, typer.Option("--out", "-o", help="checkpoint to write (.pt)")] = Path(
        "models/guardrail/slice_classifier.pt"
    ),
    sim_seeds: Annotated[str, typer.Option(help="training simulator seeds: 401-409")] = "401-409",
    validation_seeds: Annotated[str, typer.Option(help="validation seeds")] = "410-412",
    length: Annotated[float, typer.Option(help="metres per simulated survey")] = 100.0,
    epochs: Annotated[int, typer.Option(help="epochs of the classifier heads")] = 60,
) -> None:
    """Train the guardrail slice classifier on simulated surveys (camera crops + geometry)."""
    from rich.progress import Progress

    from app.pipelines.guardrail.train import train_guardrail_model

    seeds, validation = (
        _seed_list("--sim-seeds", sim_seeds),
        _seed_list("--validation-seeds", validation_seeds),
    )
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task("training", total=1.0)
        card = train_guardrail_model(
            out,
            seeds,
            validation,
            length,
            epochs,
            lambda stage, f: bar.update(task, completed=f, description=stage),
        )
    scores = card["validation"]["scores"]
    console.print(
        f"{out}: validation slice F "
        + ", ".join(f"{name} {s['f1']:.1f}" for name, s in scores.items())
    )


def _seed_list(option: str, text: str) -> list[int]:
    """ "101,102" or "101-110" (or both, comma separated) -> the seeds."""
    from app.core.errors import ConfigError

    try:
        seeds = []
        for part in filter(None, (p.strip() for p in text.split(","))):
            first, _, last = part.partition("-")
            seeds += list(range(int(first), int(last or first) + 1))
    except ValueError:
        raise ConfigError(option, f"not a list of integers: {text!r}") from None
    return seeds


user_app = typer.Typer(help="Manage the web app's users.")
cli.add_typer(user_app, name="user")


@user_app.command("add")
def user_add(
    name: Annotated[str, typer.Argument(help="login name")],
    role: Annotated[str, typer.Option(help="annotator, reviewer or admin")] = "annotator",
) -> None:
    """Create a user; the password is read from stdin (first line), never from the command."""
    from sqlmodel import Session

    from app.core.errors import ConfigError
    from app.store.db import get_engine
    from app.store.models import Role
    from app.store.users import create_user

    if role not in Role.__members__:
        raise ConfigError("--role", f"must be one of {', '.join(Role.__members__)}, got {role!r}")
    if sys.stdin.isatty():
        import getpass

        password = getpass.getpass(f"password for {name}: ")
    else:
        password = sys.stdin.readline().rstrip("\r\n")
    with Session(get_engine()) as session:
        user = create_user(session, name, password, Role(role))
    console.print(f"created user {user.username} ({user.role.value}), id {user.id}")


@cli.command()
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


EXPORTS = ("cleaned-laz", "removed-laz", "guardrails", "pillars-csv", "pillars-npz", "qa-report")


@cli.command()
def export(
    survey: Annotated[str, typer.Argument(help="survey id or name in the web app's store")],
    what: Annotated[str, typer.Argument(help=", ".join(EXPORTS))],
    out: Annotated[Path, typer.Option("--out", "-o", help="file to write")],
    mesh_format: Annotated[str, typer.Option("--mesh-format", help="guardrails: glb or obj")] = (
        "glb"
    ),
    include_model: Annotated[
        bool, typer.Option(help="pillars: add the model's pre-labels to the human labels")
    ] = False,
    overwrite: Annotated[bool, typer.Option(help="replace OUT if it exists")] = False,
) -> None:
    """Export from the web app's store (as the dashboard's downloads do): the cleaned or removed
    map of the newest clutter run, approved guardrail meshes, pillar labels, the QA report."""
    import os
    import shutil

    from sqlmodel import Session

    from app.core.errors import ConfigError
    from app.core.settings import get_settings
    from app.reports.exports import (
        clutter_map,
        csv_pieces,
        exported,
        pillar_table,
        write_guardrails_zip,
        write_pillars_npz,
    )
    from app.reports.qa_report import build_qa_report
    from app.store.db import get_engine
    from app.store.surveys import find_survey

    if what not in EXPORTS:
        raise ConfigError("WHAT", f"must be one of {', '.join(EXPORTS)} (got {what!r})")
    if mesh_format not in ("glb", "obj"):
        raise ConfigError("--mesh-format", f"must be glb or obj (got {mesh_format!r})")
    if out.exists() and not overwrite:
        raise ConfigError("--out", f"{out} exists; pass --overwrite to replace it")
    if not out.parent.is_dir():
        raise ConfigError("--out", f"{out.parent} is not a folder")
    settings = get_settings()
    partial = out.with_name(f".{out.name}.partial")
    name, details = what.replace("-", "_"), {}
    try:
        with Session(get_engine()) as session:
            record = find_survey(session, survey)
            if what in ("cleaned-laz", "removed-laz"):
                source, job_id = clutter_map(session, settings, record, what.split("-")[0])
                shutil.copyfile(source, partial)
                details = {"job_id": job_id, "file": str(source)}
            elif what == "guardrails":
                count = write_guardrails_zip(session, record, mesh_format, partial)
                name, details = "guardrails_zip", {"format": mesh_format, "models": count}
            elif what == "qa-report":
                page = build_qa_report(session, settings, record, "mmsclean export")
                partial.write_text(page, encoding="utf-8")
                details = {"bytes": len(page)}
            else:
                table = pillar_table(session, record.id, include_model)
                if what == "pillars-csv":
                    with open(partial, "w", encoding="utf-8", newline="") as f:
                        f.writelines(csv_pieces(table))
                else:
                    write_pillars_npz(table, partial)
                details = {"rows": len(table["cell_id"]), "include_model": include_model}
            label = f"survey {record.id} ({record.name})"
            exported(session, None, record, name, via="command line", out=str(out), **details)
            os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
    console.print(f"{out}: {what} of {label}")


@cli.command()
def serve(
    host: Annotated[str | None, typer.Option(help="bind address (default 127.0.0.1)")] = None,
    port: Annotated[int | None, typer.Option(help="port (default 8000)")] = None,
) -> None:
    """Start the web app (API, dashboard, viewer); /health answers once it is ready."""
    import uvicorn

    from app.api.main import create_app
    from app.core.settings import get_settings

    settings = get_settings()
    uvicorn.run(
        create_app(),
        host=host or settings.host,
        port=settings.port if port is None else port,
        log_level="info",
    )


def main() -> None:
    try:
        cli(standalone_mode=False)
    except MmscleanError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except typer.Abort:
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # usage errors (missing argument, bad option)
        show = getattr(exc, "show", None)
        if callable(show):
            show()
        else:
            print(f"error: {exc.format_message()}", file=sys.stderr)
        sys.exit(exc.exit_code or 2)


if __name__ == "__main__":
    main()
