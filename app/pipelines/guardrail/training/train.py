"""Training the slice classifier's heads and writing them with their model card (saving and
loading a checkpoint is `classifier.save_heads` / `load_heads`).

Samples are slices with their crop embedding, geometric features and label (guardrail or
other); `group` names the survey a slice came from, so validation slices never share a survey
with training slices (neighbouring slices of one guardrail are near-duplicates). The loss
weights the classes by their inverse frequency raised to `balance` (1: balanced, as the profile
classifier is trained: guardrail slices are a few percent of a street; 0: unweighted, as the
rotating one is: balanced weights bought its recall with precision on the validation surveys).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from app.metrics.classification import binary_scores
from app.pipelines.guardrail.classifier import Inputs, SliceHead, load_heads, predict, save_heads
from app.pipelines.guardrail.training.correction_choice import choose_correction, validation_slices
from app.pipelines.guardrail.training.dataset import SliceSamples, build_samples, training_data


def fit_head(
    samples: SliceSamples,
    inputs: Inputs = "image+geometry",
    epochs: int = 60,
    lr: float = 1e-3,
    weight_decay: float = 1e-4,
    batch_size: int = 256,
    seed: int = 0,
    initial: SliceHead | None = None,
    balance: float = 1.0,
) -> SliceHead:
    """Adam on the class-weighted cross entropy; returns the head in eval mode. With `initial`
    it fine-tunes a copy of that head (keeping its feature standardisation) instead of
    starting from random weights."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    geometry = torch.from_numpy(samples.geometry).float()
    if initial is not None:
        head = SliceHead(initial.inputs, initial.n_geometry)
        head.load_state_dict(initial.state_dict())
    else:
        head = SliceHead(inputs, samples.geometry.shape[1])
        head.geometry_mean.copy_(geometry.mean(dim=0))
        head.geometry_std.copy_(geometry.std(dim=0).clamp_min(1e-6))
    embedding = torch.from_numpy(samples.embedding).float()
    label = torch.from_numpy(samples.label).long()
    counts = np.bincount(samples.label, minlength=2).astype(np.float64)
    weights = torch.tensor(
        (counts.sum() / (2 * np.maximum(counts, 1))) ** balance, dtype=torch.float32
    )
    loss_fn = nn.CrossEntropyLoss(weight=weights)
    optimiser = torch.optim.Adam(head.parameters(), lr=lr, weight_decay=weight_decay)
    n = len(label)
    for _ in range(epochs):
        head.train()
        order = torch.from_numpy(rng.permutation(n))
        for start in range(0, n, batch_size):
            idx = order[start : start + batch_size]
            optimiser.zero_grad()
            loss = loss_fn(head(embedding[idx], geometry[idx]), label[idx])
            loss.backward()
            optimiser.step()
    return head.eval()


def slice_scores(head: SliceHead, samples: SliceSamples) -> dict:
    """Precision / recall / F of the guardrail class (the paper's Table 2), percent."""
    guess = predict(head, samples.embedding, samples.geometry).argmax(axis=1) == 1
    return binary_scores(samples.label == 1, guess).as_dict()


HEAD_INPUTS: tuple[Inputs, ...] = ("image+geometry", "image", "geometry")
# the head a run uses unless told (`GuardrailConfig.head`), per sensor kind: the one that holds
# on real data (rotating: geometry, decided on SemanticKITTI 05 against its fences, where the
# image heads, trained on rendered crops, called more false guardrails; models/guardrail/README.md)
DEFAULT_HEADS: dict[str, Inputs] = {"profile": "image+geometry", "rotating": "geometry"}
# the class weights' exponent per sensor kind (`fit_head`), chosen on the validation surveys
CLASS_BALANCE: dict[str, float] = {"profile": 1.0, "rotating": 0.0}


def train_guardrail_model(
    out: Path,
    seeds: list[int] | None = None,
    validation_seeds: list[int] | None = None,
    length: float | None = None,
    epochs: int = 60,
    progress=None,
    sensor: str = "profile",
    default_head: Inputs | None = None,
    balance: float | None = None,
) -> dict:
    """Fit one head per input set on the training surveys of the sensor kind's simulated data
    (`training_data`), score them on its validation surveys, save them with the card; returns
    the card. Seeds and length default to the kind's."""
    import time

    data = training_data(sensor)
    seeds = list(seeds or data.train_seeds)
    validation_seeds = list(validation_seeds or data.validation_seeds)
    length = length or data.length
    default_head = default_head or DEFAULT_HEADS[data.sensor_kind]
    balance = CLASS_BALANCE[data.sensor_kind] if balance is None else balance
    if default_head not in HEAD_INPUTS:
        raise ValueError(f"no head {default_head!r}: {', '.join(HEAD_INPUTS)}")
    held_out = (set(seeds) | set(validation_seeds)) & set(data.held_out_seeds)
    if held_out:
        raise ValueError(f"seeds {sorted(held_out)} are held out")
    started = time.perf_counter()
    train = build_samples(seeds, length, progress=progress, sensor=data.sensor_kind)
    valid = build_samples(validation_seeds, length, progress=progress, sensor=data.sensor_kind)
    built = time.perf_counter() - started
    heads, scores = {}, {}
    for inputs in HEAD_INPUTS:
        # the image heads see the slices a camera shows; the geometry head every slice, as it
        # classifies every slice no camera shows (most of a rotating scanner's)
        fit_on, score_on = (
            (train.with_crop(), valid.with_crop()) if "image" in inputs else (train, valid)
        )
        heads[inputs] = fit_head(fit_on, inputs=inputs, epochs=epochs, balance=balance)
        scores[inputs] = slice_scores(heads[inputs], score_on)
    card = {
        "model": "EfficientNet-Lite0 (ImageNet, frozen) + MLP heads; geometric slice features",
        "classes": ["other", "guardrail"],
        "sensor_kind": data.sensor_kind,
        "training": {
            "simulation_seeds": seeds,
            "length_m": length,
            "scanner": data.scanner,
            "vary_scanner": data.vary_scanner,
            "presets": {str(s): data.preset_of(s) for s in seeds},
            "slices": int(len(train.label)),
            "guardrail_slices": int(train.label.sum()),
            "slices_with_crop": int(len(train.with_crop().label)),
            "heads_trained_on": "geometry: every slice; image heads: the slices with a crop",
            "epochs": epochs,
            "class_balance": balance,
        },
        "validation": {
            "simulation_seeds": validation_seeds,
            "slices": int(len(valid.label)),
            "guardrail_slices": int(valid.label.sum()),
            "slices_with_crop": int(len(valid.with_crop().label)),
            "scores": scores,
            "scored_on": "geometry: every slice; image heads: the slices with a crop",
        },
        "held_out_seeds": list(data.held_out_seeds),
        "geometry_features": train.geometry_names,
        "default_head": default_head,
        "seconds": {"samples": round(built, 1), "total": round(time.perf_counter() - started, 1)},
    }
    save_heads(out, heads, card)
    return choose_model_correction(out, validation_seeds, length, data.sensor_kind)


def choose_model_correction(out: Path, seeds: list[int], length: float, sensor: str) -> dict:
    """Choose the adjacency correction of a saved classifier on its validation surveys
    (correction_choice.py), write it into its card and return the card."""
    heads, card = load_heads(out)
    parts = validation_slices(out, seeds, length, sensor)
    card["correction"] = choose_correction(parts, seeds)
    save_heads(out, heads, card)
    return card
