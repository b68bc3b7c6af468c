"""`mmsclean train phantom | guardrail`: a pipeline's model from simulated (and real) surveys."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli.common import config_from_options, console, seed_list, stage_progress

train_app = typer.Typer(help="Train a pipeline's model.")


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
    from app.core.errors import ConfigError
    from app.pipelines.phantom.training.from_surveys import train_phantom_model
    from app.pipelines.phantom.training.train import TrainConfig

    seeds = seed_list("--sim-seeds", sim_seeds)
    for folder in semantickitti or []:
        if not (folder / "velodyne").is_dir():
            raise ConfigError("--semantickitti", f"{folder} is not a SemanticKITTI sequence")
    config = config_from_options(
        TrainConfig,
        per_class=per_class,
        epochs=epochs,
        folds_to_run=folds_to_run,
        seed=seed,
        context=context,
    )
    with stage_progress("training") as progress:
        card = train_phantom_model(
            out, seeds, list(semantickitti or []), config, progress, sim_length=sim_length
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
