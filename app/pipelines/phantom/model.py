"""Trained phantom networks on disk: one `.pt` file holding the weights, the network's shape and
the model card (training data, class mapping, validation metrics) as JSON."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from app.core.errors import DependencyMissingError, InputError
from app.core.sensors import SensorKind
from app.pipelines.checkpoints import card_of, load_checkpoint
from app.pipelines.phantom.network import PillarCNN

MODELS = Path(__file__).resolve().parents[3] / "models" / "phantom"
DEFAULT_MODEL = MODELS / "phantom_cnn_context.pt"  # paper network + context branch (network.py)
PAPER_MODEL = MODELS / "phantom_cnn.pt"  # the paper's network alone
ROTATING_MODEL = MODELS / "phantom_rotating.pt"  # rotating scanners (HDL-64E-like), with time
# the shipped model a run picks for each sensor kind (app.pipelines.sensor_models)
SHIPPED: dict[SensorKind, Path] = {
    SensorKind.PROFILE: DEFAULT_MODEL,
    SensorKind.ROTATING: ROTATING_MODEL,
}


def save_model(path: Path, net: PillarCNN, card: dict) -> Path:
    """Write weights + shape + card (atomically); the card also goes next to it as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".partial")
    torch.save({"network": net.config(), "state_dict": net.state_dict(), "card": card}, partial)
    partial.replace(path)
    path.with_suffix(".card.json").write_text(json.dumps(card, indent=1, sort_keys=True) + "\n")
    return path


def load_model(path: Path | None = None) -> tuple[PillarCNN, dict]:
    """The network in eval mode and its card; a missing file is one clear error."""
    path = Path(path) if path is not None else DEFAULT_MODEL
    if not path.is_file():
        raise DependencyMissingError(
            f"phantom model {path} is missing: train one with `mmsclean train phantom` "
            "or pass --model"
        )
    payload = load_checkpoint(path, "phantom model")
    try:
        net = PillarCNN(**{**payload["network"], "channels": tuple(payload["network"]["channels"])})
        net.load_state_dict(payload["state_dict"])
    except (KeyError, RuntimeError, TypeError, ValueError) as exc:
        raise InputError(path, f"is not a phantom model checkpoint ({exc})") from None
    net.eval()
    return net, payload.get("card", {})


def read_card(path: Path) -> dict:
    """A checkpoint's model card: the JSON beside it, else the one inside the checkpoint."""
    return card_of(path, ".card.json", lambda p: load_model(p)[1])
