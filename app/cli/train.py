"""`mmsclean train phantom | guardrail`: a pipeline's model from simulated (and real) surveys."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli.common import config_from_options, console, seed_list, sensor_kind, stage_progress

train_app = typer.Typer(help="Train a pipeline's model.")


# what `--sensor` trains by default: where the checkpoint goes, the simulated drives, and how
# maps are cut (rotating: 10-frame maps like the real sequences, time as evidence on)
PHANTOM_DEFAULTS = {
    "profile": ("models/phantom/phantom_cnn_context.pt", "101-110,114-200,204-250", 200.0, 0),
    "rotating": ("models/phantom/phantom_rotating.pt", "601-636", 60.0, 10),
}


@train_app.command("phantom")
def train_phantom(
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="checkpoint to write (.pt; default: the shipped one)"),
    ] = None,
    sensor: Annotated[
        str, typer.Option(help="the scanner kind to train for: profile or rotating")
    ] = "profile",
    sim_seeds: Annotated[
        str | None,
        typer.Option(help="simulator seeds: 101,102 or 101-110 (presets cycle; default by kind)"),
    ] = None,
    sim_length: Annotated[
        float | None, typer.Option(help="metres per simulated survey (default by kind)")
    ] = None,
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
    passes: Annotated[
        bool | None,
        typer.Option(
            "--passes/--no-passes",
            help="time as evidence: distinct scanner passes per voxel (default: rotating on)",
        ),
    ] = None,
) -> None:
    """Train the phantom 3D CNN for one scanner kind on simulated surveys (and, for rotating
    scanners, SemanticKITTI sequences)."""
    from app.core.errors import ConfigError
    from app.pipelines.phantom.training.from_surveys import train_phantom_model
    from app.pipelines.phantom.training.train import TrainConfig

    kind = sensor_kind(sensor)
    assert kind is not None
    default_out, default_seeds, default_length, frames_per_map = PHANTOM_DEFAULTS[kind.value]
    seeds = seed_list("--sim-seeds", sim_seeds if sim_seeds is not None else default_seeds)
    for folder in semantickitti or []:
        if not (folder / "velodyne").is_dir():
            raise ConfigError("--semantickitti", f"{folder} is not a SemanticKITTI sequence")
    if semantickitti and kind.value != "rotating":
        raise ConfigError(
            "--semantickitti", "SemanticKITTI is rotating-scanner data: --sensor rotating"
        )
    config = config_from_options(
        TrainConfig,
        per_class=per_class,
        epochs=epochs,
        folds_to_run=folds_to_run,
        seed=seed,
        context=context,
        passes=kind.value == "rotating" if passes is None else passes,
        scanner="hdl64" if kind.value == "rotating" else "profile",
        frames_per_map=frames_per_map,
    )
    out = out or Path(default_out)
    with stage_progress("training") as progress:
        card = train_phantom_model(
            out, seeds, list(semantickitti or []), config, progress,
            sim_length=sim_length if sim_length is not None else default_length,
        )  # fmt: skip
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
    from app.pipelines.guardrail.training.train import train_guardrail_model

    seeds, validation = (
        seed_list("--sim-seeds", sim_seeds),
        seed_list("--validation-seeds", validation_seeds),
    )
    with stage_progress("training") as progress:
        card = train_guardrail_model(out, seeds, validation, length, epochs, progress)
    scores = card["validation"]["scores"]
    console.print(
        f"{out}: validation slice F "
        + ", ".join(f"{name} {s['f1']:.1f}" for name, s in scores.items())
    )
