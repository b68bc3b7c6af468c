"""The slice classifier: the pretrained encoder, the head's training, checkpoints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.core.errors import InputError
from app.pipelines.guardrail.classifier import (
    EMBEDDING,
    CropEncoder,
    load_heads,
    predict,
    save_heads,
)
from app.pipelines.guardrail.training.dataset import SliceSamples
from app.pipelines.guardrail.training.train import fit_head, slice_scores
from app.pipelines.tiling import placed


def _samples(n: int, seed: int) -> SliceSamples:
    """Synthetic: guardrail slices are low and long (geometry), with a shifted embedding."""
    rng = np.random.default_rng(seed)
    label = (rng.random(n) < 0.2).astype(np.int64)
    geometry = rng.normal(0, 1, (n, 3)).astype(np.float32)
    geometry[:, 0] += 6 * label  # e.g. linearity
    embedding = rng.normal(0, 1, (n, EMBEDDING)).astype(np.float32)
    embedding[:, :8] += 3.0 * label[:, None]
    return SliceSamples(embedding, geometry, label, np.zeros(n, np.int64), ["a", "b", "c"])


@pytest.mark.parametrize("inputs", ["image", "geometry", "image+geometry"])
def test_head_learns_separable_slices_and_round_trips(inputs: str, tmp_path: Path) -> None:
    head = fit_head(_samples(2000, 0), inputs=inputs, epochs=15)
    test = _samples(1000, 1)
    scores = slice_scores(head, test)
    assert scores["f1"] > 90, scores
    path = save_heads(tmp_path / "head.pt", {inputs: head}, {"name": "test"})
    heads, card = load_heads(path)
    loaded = heads[inputs]
    assert card["name"] == "test" and (tmp_path / "head.json").is_file()
    np.testing.assert_allclose(
        predict(loaded, test.embedding, test.geometry), predict(head, test.embedding, test.geometry)
    )


def test_missing_or_bad_checkpoint(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="missing"):
        load_heads(tmp_path / "none.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="not a guardrail classifier"):
        load_heads(bad)


def test_pretrained_encoder_tells_crops_apart() -> None:
    rng = np.random.default_rng(0)
    stripes = np.zeros((60, 200, 3), np.uint8)
    stripes[::10] = 255  # horizontal rails
    noise = rng.integers(0, 255, (60, 200, 3), dtype=np.uint8)
    embedded: list[int] = []  # the crops done after each batch: the step reports itself
    emb = CropEncoder(batch_size=2).embed([stripes, stripes.copy(), noise], embedded.append)
    assert embedded == [2, 3]
    assert emb.shape == (3, EMBEDDING) and np.isfinite(emb).all()
    assert np.allclose(emb[0], emb[1])
    assert np.linalg.norm(emb[0] - emb[2]) > 1.0


def test_a_step_reports_within_its_share_of_the_run() -> None:
    """A step's own 0-1 progress lands inside its share of the whole, also when it says how
    far it is in brackets (the crop embeddings of a guardrail run, issue 20); unknown steps sit
    at the end."""
    seen: list[tuple[str, float]] = []
    step = placed(
        lambda stage, f: seen.append((stage, f)),
        {"crops": (0.3, 0.4), "crop embeddings": (0.4, 0.7)},
    )
    step("crops", 0.0)
    for n in (32, 64, 96):
        step(f"crop embeddings ({n} of 96)", n / 96)
    step("classifier")
    assert [round(f, 3) for _, f in seen] == [0.3, 0.5, 0.6, 0.7, 1.0]
    assert seen[1][0] == "crop embeddings (32 of 96)"
