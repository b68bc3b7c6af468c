"""Retraining from reviewed labels: `train:phantom` fine-tunes the promoted phantom CNN on the
human pillar labels in the store, `train:guardrail` the slice classifier's heads on the slices
people labelled; both score the new and the current model on labels held out of training and
promote the new version only when it is not worse (an admin may promote any version by hand)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field
from sqlmodel import Session

from app.core.bounds import Count, Metres, Rate, RecordId, Seconds, Seed, Share
from app.core.errors import ConfigError
from app.core.settings import Settings
from app.io import open_survey
from app.io.accumulate import accumulate
from app.jobs.memory import MB, MemoryEstimate
from app.jobs.model_choice import current_version, retraining_kind
from app.jobs.phantom_training_data import (
    ClassCounts,
    held_out,
    label_counts,
    training_blocker,
)
from app.jobs.registry import JobContext, task
from app.jobs.task_config import validated
from app.metrics.classification import binary_scores
from app.metrics.splits import held_out_blocks
from app.pipelines.guardrail.classifier import (
    SliceHead,
    load_heads,
    predict,
    read_classifier_card,
    save_heads,
)
from app.pipelines.guardrail.pipeline import SHIPPED as GUARDRAIL_SHIPPED
from app.pipelines.guardrail.run import FEATURES_FILE
from app.pipelines.guardrail.segmentation import read_slice_features, slice_feature_keys
from app.pipelines.guardrail.training.dataset import SliceSamples
from app.pipelines.guardrail.training.train import fit_head
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.model import SHIPPED as PHANTOM_SHIPPED
from app.pipelines.phantom.model import load_model, read_card, save_model
from app.pipelines.phantom.priors import class_priors
from app.pipelines.phantom.training.dataset import Samples, concatenate
from app.pipelines.phantom.training.finetune import (
    LabelledPillars,
    finetune,
    labelled_pillars_per_class,
    labelled_samples,
    score,
)
from app.pipelines.phantom.training.train import TrainConfig
from app.store.guardrail_runs import latest_run, match_slices
from app.store.model_versions import register_version
from app.store.models import Pipeline
from app.store.pillar_labels import STORE_GRID
from app.store.pillar_reads import human_labels_since, reviewed_class_counts
from app.store.surveys import get_survey
from app.store.training_labels import human_pillar_labels, reviewed_slices

PHANTOM_SAMPLE_BYTES = 30 * 24 * 24 + 6 * 31 * 31  # a window's counts + context bands, uint8


class PhantomRetrainConfig(BaseModel):
    survey_ids: list[RecordId] | None = Field(
        None, max_length=10_000, description="surveys whose labels to use; all"
    )
    holdout: Share = Field(0.2, gt=0, lt=1, description="share of map blocks held out")
    block_size: Metres = Field(10.0, gt=0, description="metres: blocks kept whole by the split")
    rotations: int = Field(4, ge=1, le=16, description="copies of the map, first unrotated")
    epochs: int = Field(4, ge=1, le=100)
    per_class: Count = Field(5000, ge=1, description="balanced samples per labelled class")
    lr: Rate = Field(0.005, gt=0, description="fine-tuning SGD rate (below training's 0.05)")
    seed: Seed = 0
    time_limit: Seconds | None = Field(None, description="seconds of training at most")
    min_labels: Count = Field(50, ge=1, description="fewer human labels: refuse to train")
    min_classes: int = Field(
        2, ge=1, le=4, description="fewer classes among the training labels: refuse to train"
    )
    min_class_labels: Count = Field(
        50,
        ge=1,
        description="a class with fewer labelled pillars in training is left out (as the base "
        "model knew it): a few pillars copied up to the largest class's size teach those pillars",
    )
    trigger: Literal["on demand", "labels"] = Field(
        "on demand", description="who asked: a user, or the new-labels trigger"
    )
    sensor_kind: Literal["rotating", "profile"] | None = Field(
        None, description="the scanner kind to retrain for; default: the labelled surveys' one"
    )


def check_phantom_config(config: dict[str, Any], _settings: Settings) -> None:
    validated(PhantomRetrainConfig, config)


def estimate_phantom(session: Session, _survey: int | None, config: dict[str, Any]):
    """train:phantom's memory: the labelled windows (each rotated copy) and the balanced
    training samples (per class)."""
    cfg = validated(PhantomRetrainConfig, config)
    labels = human_labels_since(session, None)
    estimate = MemoryEstimate(f"{labels:,} human pillar labels")
    estimate.add(
        "config.rotations",
        labels * cfg.rotations * PHANTOM_SAMPLE_BYTES / MB,
        f"{cfg.rotations} copies of every labelled window",
    )
    return estimate.add(
        "config.per_class",
        4 * cfg.per_class * PHANTOM_SAMPLE_BYTES / MB,
        f"{cfg.per_class:,} balanced samples per class",
    )


def refuse_if_blocked(counts: ClassCounts, cfg: PhantomRetrainConfig) -> None:
    """The job fails with the one line `training_blocker` gives (the trigger's check)."""
    blocked = training_blocker(counts, cfg)
    if blocked is not None:
        raise ConfigError("labels", blocked)


def retraining_priors(
    reviewed: np.ndarray, base_card: dict[str, Any], surveys: list[int]
) -> tuple[list[float] | None, str]:
    """The new version's class priors (priors.py): the labelled surveys' class shares as
    reviewed so far, since the model is retrained for the streets its operators label, which the
    base's training maps may not resemble (simulated drives hold about a third phantom pillars,
    real streets a few per cent); the base's priors when no labelled survey had a phantom run."""
    if reviewed.sum() == 0:
        return base_card.get("class_priors"), str(base_card.get("class_priors_from", "base"))
    origin = (
        f"surveys {surveys} as reviewed: {int(reviewed.sum()):,} pillars their last phantom run "
        "judged, each with its human label where one was given, else its pre-label"
    )
    return class_priors(reviewed).round(5).tolist(), origin


def class_counts(parts: list[Samples]) -> np.ndarray:
    """(4,) distinct labelled pillars per class over PARTS (rotated copies count once)."""
    return sum((labelled_pillars_per_class(p) for p in parts), np.zeros(4, np.int64))


def phantom_training_labels(session: Session, cfg: PhantomRetrainConfig):
    """(sensor kind, survey id -> human labels) that `train:phantom` trains on; ConfigError
    with the one line that says why they cannot train it (checked before any map is opened,
    and by the dashboard before it offers the button)."""
    labels = human_pillar_labels(session, cfg.survey_ids)
    kind, usable = retraining_kind(session, labels, cfg.sensor_kind)
    labels = {sid: labels[sid] for sid in usable}
    refuse_if_blocked(label_counts(labels, cfg), cfg)
    return kind, labels


@task("train:phantom", check=check_phantom_config, estimate=estimate_phantom)
def train_phantom(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    cfg = validated(PhantomRetrainConfig, config)
    phantom = PhantomConfig()
    with Session(context.engine) as session:
        kind, labels = phantom_training_labels(session, cfg)
        total = sum(len(s.cells) for s in labels.values())
        reviewed = sum(
            (reviewed_class_counts(session, sid) for sid in labels), np.zeros(4, np.int64)
        )
        surveys = {}
        for survey_id in labels:
            record = get_survey(session, survey_id)
            surveys[survey_id] = (record.name, record.source_path, record.format)
        what = f"retraining on the labels of surveys {sorted(labels)}"
        base = current_version(session, Pipeline.phantom, kind, PHANTOM_SHIPPED, read_card, what)
        base_path, base_id = Path(base.checkpoint_path), base.id
    base_net, base_card = load_model(base_path)
    context.log.info(
        "fine-tuning %s on %d human labels of %d surveys", base_path, total, len(labels)
    )

    rng = np.random.default_rng(cfg.seed)
    train_parts, val_parts = [], []
    for k, (survey_id, survey_labels) in enumerate(labels.items()):
        context.progress(0.3 * k / len(labels), f"samples of survey {survey_id}")
        name, source, fmt = surveys[survey_id]
        amap = accumulate(open_survey(source, fmt), with_passes=base_net.passes)
        if base_net.passes and amap.passes is None:
            raise ConfigError("labels", f"survey {name} has no point times; the model reads them")
        cells, classes = survey_labels.cells, survey_labels.classes
        pillars = np.stack(STORE_GRID.decode(cells), axis=1)
        held = held_out(survey_labels, cfg)
        context_branch = base_net.context > 0
        for part, mask, rotations in ((train_parts, ~held, cfg.rotations), (val_parts, held, 1)):
            if mask.any():
                lmap = LabelledPillars(name, amap.xyz, pillars[mask], classes[mask], amap.passes)
                part.append(labelled_samples(lmap, phantom, rotations, rng, context_branch))
    # a pillar with no points gives no sample: check again with what the maps gave
    sampled = ClassCounts(total, class_counts(train_parts), class_counts(val_parts), True)
    refuse_if_blocked(sampled, cfg)
    train_samples, val_samples = concatenate(train_parts), concatenate(val_parts)
    context.log.info(
        "samples: train %s, validation %s",
        train_samples.class_counts(),
        val_samples.class_counts(),
    )

    started = time.perf_counter()
    train_config = TrainConfig(
        epochs=cfg.epochs,
        lr=cfg.lr,
        seed=cfg.seed,
        time_limit=cfg.time_limit,
        block_size=cfg.block_size,
        per_class=cfg.per_class,
    )
    result = finetune(
        train_samples,
        base_net,
        train_config,
        cfg.per_class,
        lambda stage, f: context.progress(0.3 + 0.6 * f, stage),
        cfg.min_class_labels,
    )
    context.progress(0.92, "validation on held-out labels")
    new_scores, base_scores = score(result.net, val_samples), score(base_net, val_samples)
    promote = new_scores.macro.f1 >= base_scores.macro.f1
    name = f"phantom-job{context.job_id}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
    checkpoint = context.settings.data_dir / "models" / "phantom" / f"{name}.pt"
    priors, priors_from = retraining_priors(reviewed, base_card, sorted(labels))
    card = {
        **result.card,
        "sensor_kind": kind.value,
        "class_priors": priors,
        "class_priors_from": priors_from,
        "fine_tuned_from": str(base_path),
        "held_out_validation": new_scores.as_dict(),
        "base_on_held_out": base_scores.as_dict(),
    }
    save_model(checkpoint, result.net, card)
    metrics = {
        "validation": new_scores.as_dict(),
        "baseline": base_scores.as_dict(),
        "base_version_id": base_id,
        "validation_labels": int(len(val_samples)),
        "training_seconds": round(time.perf_counter() - started, 1),
    }
    trained_on = {
        "surveys": sorted(labels),
        "sensor_kind": kind.value,
        "human_labels": total,
        "train_samples": train_samples.class_counts(),
        "validation_samples": val_samples.class_counts(),
        "config": cfg.model_dump(),
    }
    with Session(context.engine) as session:
        version = register_version(
            session, Pipeline.phantom, name, checkpoint, metrics, trained_on,
            context.job_id, promote, kind,
        )  # fmt: skip
    context.progress(1.0, "promoted" if promote else "kept the current version (new one worse)")
    return {
        "files": {"checkpoint": str(checkpoint), "card": str(checkpoint.with_suffix(".card.json"))},
        "model_version_id": version.id,
        "promoted": promote,
        "validation_macro_f1": new_scores.macro.f1,
        "baseline_macro_f1": base_scores.macro.f1,
    }


# --- guardrail ----------------------------------------------------------------------------


class GuardrailRetrainConfig(BaseModel):
    survey_ids: list[RecordId] | None = Field(
        None, max_length=10_000, description="surveys whose slices to use; all"
    )
    holdout: Share = Field(0.25, gt=0, lt=1, description="share of road blocks held out")
    block_size: Metres = Field(20.0, gt=0, description="metres of road kept whole by the split")
    epochs: int = Field(30, ge=1, le=500)
    lr: Rate = Field(3e-4, gt=0, description="fine-tuning Adam rate (training: 1e-3)")
    seed: Seed = 0
    min_labels: Count = Field(20, ge=1, description="fewer reviewed slices: refuse to train")
    trigger: Literal["on demand", "labels"] = "on demand"
    sensor_kind: Literal["rotating", "profile"] | None = Field(
        None, description="the scanner kind to retrain for; default: the reviewed surveys' one"
    )


def check_guardrail_config(config: dict[str, Any], _settings: Settings) -> None:
    validated(GuardrailRetrainConfig, config)


def _slice_samples(
    features: Path, reviewed: np.ndarray, survey_id: int
) -> tuple[SliceSamples, np.ndarray]:
    """The reviewed slices' classifier inputs from a run's saved features (with whether a
    camera crop showed each) and their stations (slices missing from the run are left out)."""
    component, slice_index = slice_feature_keys(features)
    at = match_slices(
        reviewed[:, 0].astype(np.int64), reviewed[:, 1].astype(np.int64), component, slice_index
    )
    found = at >= 0
    f = read_slice_features(features, at[found])
    return (
        SliceSamples(
            embedding=f["embedding"].astype(np.float32),
            geometry=f["geometry"].astype(np.float32),
            label=reviewed[found, 3].astype(np.int64),
            group=np.full(int(found.sum()), survey_id, dtype=np.int64),
            geometry_names=[str(n) for n in f["geometry_names"]],
            has_crop=f["has_crop"].astype(bool),
        ),
        reviewed[found, 2],
    )


def pipeline_scores(heads: dict[str, SliceHead], samples: SliceSamples, head: str):
    """Guardrail-slice scores as the pipeline predicts with `head` (the model's default): that
    head where a camera crop shows the slice (or the head needs none), the geometry head
    elsewhere."""
    guess = np.zeros(len(samples.label), dtype=bool)
    with_head = samples.crop if "image" in head else np.ones(len(samples.label), dtype=bool)
    for name, where in ((head, with_head), ("geometry", ~with_head)):
        if where.any():
            probability = predict(heads[name], samples.embedding[where], samples.geometry[where])
            guess[where] = probability[:, 1] >= 0.5
    scores = binary_scores(samples.label == 1, guess)
    accuracy = 100.0 * float((guess == (samples.label == 1)).mean()) if len(guess) else 0.0
    return {**scores.as_dict(), "accuracy": accuracy}


def guardrail_training_slices(session: Session, cfg: GuardrailRetrainConfig):
    """(sensor kind, survey id -> reviewed slices) that `train:guardrail` trains on;
    ConfigError when they are too few (checked by the dashboard before it offers the button)."""
    reviewed = reviewed_slices(session, cfg.survey_ids)
    kind, usable = retraining_kind(session, reviewed, cfg.sensor_kind)
    reviewed = {sid: reviewed[sid] for sid in usable}
    total = sum(len(r) for r in reviewed.values())
    if total < cfg.min_labels:
        raise ConfigError(
            "labels", f"{total} reviewed guardrail slices; retraining needs {cfg.min_labels}"
        )
    return kind, reviewed


@task("train:guardrail", check=check_guardrail_config)
def train_guardrail(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """Fine-tune the promoted slice classifier's heads on the slices people labelled (the
    frozen image encoder's embeddings saved by each run), score new and current heads on
    held-out road blocks, promote when not worse."""
    cfg = validated(GuardrailRetrainConfig, config)
    with Session(context.engine) as session:
        kind, reviewed = guardrail_training_slices(session, cfg)
        total = sum(len(r) for r in reviewed.values())
        runs = {s: latest_run(session, s) for s in reviewed}
        base = current_version(
            session, Pipeline.guardrail, kind, GUARDRAIL_SHIPPED, read_classifier_card,
            f"retraining on the slices of surveys {sorted(reviewed)}",
        )  # fmt: skip
        base_path = Path(base.checkpoint_path)
    heads, base_card = load_heads(base_path)
    train_parts, val_parts = [], []
    for k, (survey_id, rows) in enumerate(reviewed.items()):
        context.progress(0.2 * k / len(reviewed), f"slices of survey {survey_id}")
        run = runs[survey_id]
        features = None if run is None else Path(run.stage_path).with_name(FEATURES_FILE)
        if features is None or not features.is_file():
            context.log.warning("survey %d: no slice features of its last run; skipped", survey_id)
            continue
        samples, station = _slice_samples(features, rows, survey_id)
        held = held_out_blocks(station[:, None], cfg.block_size, cfg.holdout, cfg.seed)
        train_parts.append(samples.subset(~held))
        val_parts.append(samples.subset(held))
    if not train_parts:
        raise ConfigError("labels", "no reviewed slice has the features of its run; rerun it")
    train_set = SliceSamples.concatenate(train_parts)
    val_set = SliceSamples.concatenate(val_parts)
    new_heads = {}
    for i, (name, head) in enumerate(heads.items()):
        context.progress(0.2 + 0.7 * i / len(heads), f"fine-tuning the {name} head")
        subset = train_set.with_crop() if "image" in name else train_set
        if len(subset.label) == 0:
            new_heads[name] = head
            continue
        new_heads[name] = fit_head(
            subset, name, epochs=cfg.epochs, lr=cfg.lr, seed=cfg.seed, initial=head,
            balance=float(base_card.get("training", {}).get("class_balance", 1.0)),
        )  # fmt: skip
    default_head = base_card.get("default_head", "image+geometry")
    new_scores = pipeline_scores(new_heads, val_set, default_head)
    base_scores = pipeline_scores(heads, val_set, default_head)
    promote = (new_scores["f1"], new_scores["accuracy"]) >= (
        base_scores["f1"],
        base_scores["accuracy"],
    )
    name = f"guardrail-job{context.job_id}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
    checkpoint = context.settings.data_dir / "models" / "guardrail" / f"{name}.pt"
    card = {
        **{k: v for k, v in base_card.items() if k != "created"},
        "sensor_kind": kind.value,
        "fine_tuned_from": str(base_path),
        "fine_tuning": {
            "reviewed_slices": total,
            "train_slices": int(len(train_set.label)),
            "validation_slices": int(len(val_set.label)),
            "config": cfg.model_dump(),
        },
        "held_out_validation": new_scores,
        "base_on_held_out": base_scores,
    }
    save_heads(checkpoint, new_heads, card)
    metrics = {
        "validation": new_scores,
        "baseline": base_scores,
        "base_version_id": base.id,
        "validation_slices": int(len(val_set.label)),
    }
    trained_on = {
        "surveys": sorted(reviewed),
        "sensor_kind": kind.value,
        "reviewed_slices": total,
        "config": cfg.model_dump(),
    }
    with Session(context.engine) as session:
        version = register_version(
            session, Pipeline.guardrail, name, checkpoint, metrics, trained_on,
            context.job_id, promote, kind,
        )  # fmt: skip
    context.progress(1.0, "promoted" if promote else "kept the current version (new one worse)")
    return {
        "files": {"checkpoint": str(checkpoint)},
        "model_version_id": version.id,
        "promoted": promote,
        "validation_f1": new_scores["f1"],
        "baseline_f1": base_scores["f1"],
    }
