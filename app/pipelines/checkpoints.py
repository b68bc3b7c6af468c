"""Reading a checkpoint file without trusting it.

A `.pt` file is a pickle: loaded without the weights-only unpickler it can run any code it
names (an uploaded `evil.pt` would run as the server's user). Every checkpoint of the project
therefore loads with `weights_only=True`, which only rebuilds tensors and plain types (dict,
list, str, numbers); anything else is refused with one line naming the file.
"""

from __future__ import annotations

import json
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from app.core.errors import InputError


def load_checkpoint(path: Path, what: str) -> dict[str, Any]:
    """The checkpoint's top-level dict (tensors on the CPU); InputError naming `path` when it
    holds anything but tensors and plain types, is no dict, or is unreadable."""
    path = Path(path)
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise InputError(
            path, f"not a {what} checkpoint: it holds objects other than tensors and plain types"
        ) from None
    except Exception as exc:  # truncated, not a zip or pickle, ...: any failure means unusable
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(path, f"not a {what} checkpoint ({reason})") from None
    if not isinstance(blob, dict):
        raise InputError(path, f"not a {what} checkpoint (holds a {type(blob).__name__})")
    return blob


def card_of(path: Path, sidecar_suffix: str, embedded: Callable[[Path], dict]) -> dict:
    """A checkpoint's model card: the JSON beside it (`path` with `sidecar_suffix`), else the
    one inside the checkpoint as `embedded` reads it."""
    sidecar = Path(path).with_suffix(sidecar_suffix)
    if sidecar.is_file():
        return json.loads(sidecar.read_text())
    return embedded(Path(path))
