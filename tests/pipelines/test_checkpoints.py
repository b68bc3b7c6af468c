"""Checkpoints are data, never code: every `torch.load` of the project reads with
weights_only=True, the shipped models load that way, and anything else in a file is one line."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from app.core.errors import InputError
from app.pipelines.checkpoints import load_checkpoint
from app.pipelines.guardrail.classifier import load_heads, save_heads

ROOT = Path(__file__).resolve().parents[2]
SEARCHED = ("app", "bench", "tests", "docs", "models")
TEXT_SUFFIXES = {".py", ".md", ".txt", ".json", ".sh", ".ipynb", ".toml", ".cfg", ".yml", ".yaml"}
UNSAFE = "weights_only=" + "False"  # spelled apart so this file does not match itself


def call_text(source: str, start: int) -> str:
    """The text of the call whose '(' is at `start`, up to its matching ')'."""
    depth = 0
    for end in range(start, len(source)):
        depth += {"(": 1, ")": -1}.get(source[end], 0)
        if depth == 0:
            return source[start : end + 1]
    return source[start:]


def test_every_torch_load_reads_weights_only() -> None:
    problems = []
    for top in SEARCHED:
        for path in sorted((ROOT / top).rglob("*")):
            if path.suffix not in TEXT_SUFFIXES or not path.is_file():
                continue
            source = path.read_text(errors="replace")
            where = path.relative_to(ROOT)
            if UNSAFE in source:
                problems.append(f"{where}: {UNSAFE}")
            for match in re.finditer(r"torch\.load\s*\(", source):
                call = call_text(source, match.end() - 1)
                if not re.search(r"weights_only\s*=\s*True", call):
                    line = source.count("\n", 0, match.start()) + 1
                    problems.append(f"{where}:{line}: torch.load without weights_only=True")
    assert problems == []


@pytest.mark.parametrize("path", sorted((ROOT / "models").rglob("*.pt")), ids=str)
def test_shipped_checkpoints_load_as_data(path: Path) -> None:
    blob = torch.load(path, map_location="cpu", weights_only=True)
    assert isinstance(blob, dict) and "card" in blob


def test_saved_heads_load_as_data(tmp_path: Path) -> None:
    heads, card = load_heads(ROOT / "models" / "guardrail" / "slice_classifier.pt")
    card = {**card, "note": Path("not/plain"), "scores": {"f1": torch.tensor(0.5).item()}}
    path = save_heads(tmp_path / "heads.pt", heads, card)
    again, saved_card = load_heads(path)
    assert saved_card["note"] == "not/plain"  # the card was stored as plain types
    for name, head in heads.items():
        for key, value in head.state_dict().items():
            assert torch.equal(again[name].state_dict()[key], value)


def test_unreadable_files_are_one_line(tmp_path: Path) -> None:
    for name, data in (("empty.pt", b""), ("text.pt", b"hello"), ("zip.pt", b"PK\x03\x04xx")):
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(InputError) as caught:
            load_checkpoint(path, "test")
        assert str(caught.value).startswith(f"{path}: not a test checkpoint")
        assert "\n" not in str(caught.value)
    listed = tmp_path / "list.pt"
    torch.save([1, 2], listed)
    with pytest.raises(InputError, match="holds a list"):
        load_checkpoint(listed, "test")
