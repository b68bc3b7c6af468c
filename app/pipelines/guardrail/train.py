"""Training the slice classifier's head, saving and loading it with its model card.

Samples are slices with their crop embedding, geometric features and label (guardrail or
other); `group` names the survey a slice came from, so validation slices never share a survey
with training slices (neighbouring slices of one guardrail are near-duplicates). The loss
weights the classes by their inverse frequency: guardrail slices are a few percent of a street.
"""

from __future__ import annotations

import datetime
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from app.core.errors import InputError
from app.metrics.classification import binary_scores
from app.pipelines.guardrail.classifier import Inputs, SliceHead, predict


@dataclass
class SliceSamples:
    embedding: np.ndarray  # (N, 1280) float32
    geometry: np.ndarray  # (N, G) float32
    label: np.ndarray  # (N,) int64: 1 guardrail, 0 other
    group: np.ndarray  # (N,) int64 survey id
    geometry_names: list[str]

    def subset(self, keep: np.ndarray) -> SliceSamples:
        return SliceSamples(
            self.embedding[keep],
            self.geometry[keep],
            self.label[keep],
            self.group[keep],
            self.geometry_names,
        )


def fit_head(
    samples: SliceSamples,
    inputs: Inputs = "image+geometry",
    epochs: int = 60,
    lr: float = 1e-3,
    weight_decay: float = 1e-4,
    batch_size: int = 256,
    seed: int = 0,
) -> SliceHead:
    """Adam on the class-weighted cross entropy; returns the head in eval mode."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    head = SliceHead(inputs, samples.geometry.shape[1])
    geometry = torch.from_numpy(samples.geometry).float()
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


def save_head(path: Path, head: SliceHead, card: dict) -> Path:
    """Checkpoint (weights + shape + card) and the card as JSON beside it; written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    card = {"created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"), **card}
    partial = path.with_suffix(".partial")
    torch.save(
        {
            "state_dict": head.state_dict(),
            "inputs": head.inputs,
            "n_geometry": head.n_geometry,
            "card": card,
        },
        partial,
    )
    os.replace(partial, path)
    card_path = path.with_suffix(".json")
    card_path.write_text(json.dumps(card, indent=1, sort_keys=True) + "\n")
    return path


def load_head(path: Path) -> tuple[SliceHead, dict]:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "guardrail classifier checkpoint is missing")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=False)
        head = SliceHead(blob["inputs"], int(blob["n_geometry"]))
        head.load_state_dict(blob["state_dict"])
    except Exception as exc:  # any failure means the file is unusable
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(path, f"not a guardrail classifier checkpoint ({reason})") from None
    return head.eval(), blob.get("card", {})
