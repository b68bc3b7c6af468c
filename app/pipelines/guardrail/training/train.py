"""Training the slice classifier's heads and writing them with their model card (saving and
loading a checkpoint is `classifier.save_heads` / `load_heads`).

Samples are slices with their crop embedding, geometric features and label (guardrail or
other); `group` names the survey a slice came from, so validation slices never share a survey
with training slices (neighbouring slices of one guardrail are near-duplicates). The loss
weights the classes by their inverse frequency: guardrail slices are a few percent of a street.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from app.metrics.classification import binary_scores
from app.pipelines.guardrail.classifier import Inputs, SliceHead, predict, save_heads
from app.pipelines.guardrail.training.dataset import (
    HELD_OUT_SEEDS,
    TRAIN_SEEDS,
    VALIDATION_SEEDS,
    SliceSamples,
    build_samples,
)


def fit_head(
    samples: SliceSamples,
    inputs: Inputs = "image+geometry",
    epochs: int = 60,
    lr: float = 1e-3,
    weight_decay: float = 1e-4,
    batch_size: int = 256,
    seed: int = 0,
    initial: SliceHead | None = None,
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
    weights = torch.tensor(counts.sum() / (2 * np.maximum(counts, 1)), dtype=torch.float32)
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


def train_guardrail_model(
    out: Path,
    seeds: list[int] | None = None,
    validation_seeds: list[int] | None = None,
    length: float = 100.0,
    epochs: int = 60,
    progress=None,
) -> dict:
    """Fit one head per input set on the training surveys, score them on the validation
    surveys, save them with the card; returns the card."""
    import time

    seeds = list(seeds or TRAIN_SEEDS)
    validation_seeds = list(validation_seeds or VALIDATION_SEEDS)
    if set(seeds) & set(HELD_OUT_SEEDS):
        raise ValueError(f"seeds {sorted(set(seeds) & set(HELD_OUT_SEEDS))} are held out")
    started = time.perf_counter()
    train = build_samples(seeds, length, progress=progress)
    valid = build_samples(validation_seeds, length, progress=progress)
    built = time.perf_counter() - started
    heads, scores = {}, {}
    for inputs in HEAD_INPUTS:
        heads[inputs] = fit_head(train, inputs=inputs, epochs=epochs)
        scores[inputs] = slice_scores(heads[inputs], valid)
    card = {
        "model": "EfficientNet-Lite0 (ImageNet, frozen) + MLP heads; geometric slice features",
        "classes": ["other", "guardrail"],
        "training": {
            "simulation_seeds": seeds,
            "length_m": length,
            "scanner": "profile",
            "slices": int(len(train.label)),
            "guardrail_slices": int(train.label.sum()),
            "epochs": epochs,
        },
        "validation": {
            "simulation_seeds": validation_seeds,
            "slices": int(len(valid.label)),
            "guardrail_slices": int(valid.label.sum()),
            "scores": scores,
        },
        "geometry_features": train.geometry_names,
        "default_head": "image+geometry",
        "seconds": {"samples": round(built, 1), "total": round(time.perf_counter() - started, 1)},
    }
    save_heads(out, heads, card)
    return card
