"""`mmsclean train phantom | guardrail | clutter-shapes`: a pipeline's model from simulated (and
real) surveys."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli.common import config_from_options, console, seed_list, sensor_kind, stage_progress

train_app = typer.Typer(help="Train a pipeline's model.")

OutOption = Annotated[
    Path | None,
    typer.Option("--out", "-o", help="checkpoint to write (.pt; default: the shipped one)"),
]
KindOption = Annotated[
    str, typer.Option("--sensor", help="the scanner kind to train for: profile or rotating")
]


# what `--sensor` trains by default (the shipped models' recipes): where the checkpoint goes,
# the simulated drives and their length, how maps are cut (rotating: 10-frame maps like the
# real sequences, time as evidence on), pillars per class, epochs
PHANTOM_DEFAULTS = {
    "profile": (
        "models/phantom/phantom_cnn_context.pt",
        "101-110,114-200,204-250",
        200.0,
        0,
        20_000,
        10,
    ),
    "rotating": ("models/phantom/phantom_rotating.pt", "601-612", 60.0, 10, 3_000, 6),
}


@train_app.command("phantom")
def train_phantom(
    out: OutOption = None,
    sensor: KindOption = "profile",
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
    per_class: Annotated[
        int | None, typer.Option(help="pillars per class (paper: 10,000; default by kind)")
    ] = None,
    epochs: Annotated[int | None, typer.Option(help="training epochs (default by kind)")] = None,
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
    (
        default_out,
        default_seeds,
        default_length,
        frames_per_map,
        default_per_class,
        default_epochs,
    ) = PHANTOM_DEFAULTS[kind.value]
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
        per_class=per_class if per_class is not None else default_per_class,
        epochs=epochs if epochs is not None else default_epochs,
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


# where `--sensor` writes by default; the simulated surveys it trains on by default are the
# kind's in app.pipelines.guardrail.training.dataset.TRAINING_DATA (profile: seeds 401-409,
# validation 410-412, 100 m; rotating: HDL-64E-class scanners drawn from seeds 701-709,
# validation 781-782, 30 m)
GUARDRAIL_DEFAULTS = {
    "profile": "models/guardrail/slice_classifier.pt",
    "rotating": "models/guardrail/slice_classifier_rotating.pt",
}


@train_app.command("guardrail")
def train_guardrail(
    out: OutOption = None,
    sensor: KindOption = "profile",
    sim_seeds: Annotated[
        str | None, typer.Option(help="training simulator seeds: 401-409 (default by kind)")
    ] = None,
    validation_seeds: Annotated[
        str | None, typer.Option(help="validation seeds (default by kind)")
    ] = None,
    length: Annotated[
        float | None, typer.Option(help="metres per simulated survey (default by kind)")
    ] = None,
    epochs: Annotated[int, typer.Option(help="epochs of the classifier heads")] = 60,
    default_head: Annotated[
        str | None,
        typer.Option(
            help="the head runs use unless told: image+geometry, image, geometry "
            "(default by kind: the one that holds on real data)"
        ),
    ] = None,
    correction_only: Annotated[
        bool,
        typer.Option(
            "--correction-only",
            help="keep the classifier at --out and only choose its adjacency correction "
            "(threshold, max gap, max isolated, keep confident) on the validation surveys again",
        ),
    ] = False,
) -> None:
    """Train the guardrail slice classifier for one scanner kind on simulated surveys (camera
    crops + geometry; rotating: HDL-64E-class scanners drawn from the seed), then choose its
    adjacency correction on the validation surveys."""
    from app.core.errors import ConfigError
    from app.pipelines.guardrail.training.dataset import training_data
    from app.pipelines.guardrail.training.train import (
        HEAD_INPUTS,
        choose_model_correction,
        train_guardrail_model,
    )

    kind = sensor_kind(sensor)
    assert kind is not None
    seeds = seed_list("--sim-seeds", sim_seeds) if sim_seeds is not None else None
    validation = (
        seed_list("--validation-seeds", validation_seeds) if validation_seeds is not None else None
    )
    if default_head is not None and default_head not in HEAD_INPUTS:
        raise ConfigError("--default-head", f"{default_head!r}: use {', '.join(HEAD_INPUTS)}")
    out = out or Path(GUARDRAIL_DEFAULTS[kind.value])
    if correction_only:
        data = training_data(kind.value)
        card = choose_model_correction(
            out, validation or list(data.validation_seeds), length or data.length, kind.value
        )
        chosen = card["correction"]
        console.print(
            f"{out}: correction threshold {chosen['threshold']}, max gap {chosen['max_gap']}, "
            f"max isolated {chosen['max_isolated']}, confident lone slices kept from "
            f"{chosen.get('keep_confident') or 'never'}: validation slice F "
            f"{chosen['validation_slice_f']:.1f} (the paper's settings "
            f"{chosen['paper_validation_slice_f']:.1f})"
        )
        return
    with stage_progress("training") as progress:
        try:
            card = train_guardrail_model(
                out, seeds, validation, length, epochs, progress,
                sensor=kind.value, default_head=default_head,  # type: ignore[arg-type]
            )  # fmt: skip
        except ValueError as exc:  # held-out seeds
            raise ConfigError("--sim-seeds", str(exc)) from None
    scores = card["validation"]["scores"]
    console.print(
        f"{out} ({card['sensor_kind']}, default head {card['default_head']}): validation "
        "slice F "
        + ", ".join(f"{name} {s['f1']:.1f}" for name, s in scores.items())
        + f"; corrected {card['correction']['validation_slice_f']:.1f}"
    )


@train_app.command("clutter-shapes")
def train_clutter_shapes(
    out: OutOption = None,
    sim_seeds: Annotated[str, typer.Option(help="training simulator seeds")] = "301-328",
    validation_seeds: Annotated[str, typer.Option(help="validation seeds")] = "329-335",
    epochs: Annotated[int, typer.Option(help="epochs of the classifier")] = 30,
    scenes: Annotated[
        str | None,
        typer.Option(help="the simulated scenes a seed cycles through (seed % count), by commas"),
    ] = None,
    vegetation: Annotated[
        bool, typer.Option(help="simulated streets with hedges and bushes (leaves, not shells)")
    ] = False,
    semantickitti: Annotated[
        list[Path] | None,
        typer.Option(help="labelled SemanticKITTI sequence folder to learn from too (repeatable)"),
    ] = None,
    real_weight: Annotated[
        float,
        typer.Option(min=1.0, max=1000.0, help="weight of a real cluster beside a simulated"),
    ] = 10.0,
) -> None:
    """Train the clutter pipeline's vehicle shape classifier (rotating scanners) on simulated
    streets (object-sized clusters labelled vehicle or other by the simulator, 3D only) and on
    the clusters of labelled real sequences, if given."""
    from app.core.errors import ConfigError
    from app.io import open_survey
    from app.pipelines.clutter.shapes import ROTATING_MODEL
    from app.pipelines.clutter.training.shapes import (
        LENGTH,
        SCENES,
        THRESHOLD,
        labelled_samples,
        samples,
        scene_cycle,
        scores,
        train_shapes,
        with_real,
    )

    seeds = seed_list("--sim-seeds", sim_seeds)
    validation = seed_list("--validation-seeds", validation_seeds)
    if set(seeds) & set(validation):
        raise ConfigError("--validation-seeds", "the validation seeds overlap the training seeds")
    for folder in semantickitti or []:
        if not (folder / "velodyne").is_dir() or not (folder / "labels").is_dir():
            raise ConfigError(
                "--semantickitti", f"{folder} is not a labelled SemanticKITTI sequence"
            )
    cycle = scene_cycle(scenes) if scenes else SCENES
    out = out or ROTATING_MODEL
    with stage_progress("training") as progress:
        progress("simulated streets", 0.0)
        simulated = samples(seeds, scenes=cycle, vegetation=vegetation)
        valid_inputs, vy, _ = samples(validation, scenes=cycle, vegetation=vegetation)
        real = labelled_samples([open_survey(f, "semantickitti") for f in semantickitti or []])
        inputs, y, weight = with_real(simulated, real, real_weight)
        progress("training", 0.5)
        card = {
            "sensor_kind": "rotating",
            "simulation": {"scanner": "hdl64", "vary_scanner": True, "seeds": seeds,
                "validation_seeds": validation, "scenes": list(cycle), "length_m": LENGTH,
                "vegetation": vegetation},
            "real": {"sequences": [f.name for f in semantickitti or []],
                "clusters": int(len(real[1])), "vehicles": int(real[1].sum()),
                "weight": real_weight},
            "threshold": THRESHOLD,
            "epochs": epochs,
        }  # fmt: skip
        model = train_shapes(inputs, y, epochs, card=card, weight=weight)
        model.card["training"] = scores(model, inputs, y, THRESHOLD)
        model.card["validation"] = scores(model, valid_inputs, vy, THRESHOLD)
        model.save(out)
    valid = model.card["validation"]
    console.print(
        f"{out}: {len(y)} training clusters ({int(y.sum())} vehicles); validation at "
        f"P >= {THRESHOLD}: precision {valid['precision']:.1f} %, recall {valid['recall']:.1f} %"
    )
