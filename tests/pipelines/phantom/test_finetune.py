"""Fine-tuning the promoted phantom CNN on an operator's pillar labels (train:phantom's core)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from app.geometry.ground import estimate_ground
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.network import PillarCNN
from app.pipelines.phantom.pillars import build_pillar_map
from app.pipelines.phantom.training.finetune import (
    LabelledPillars,
    epoch_split,
    finetune,
    labelled_pillars_per_class,
    labelled_samples,
)
from app.pipelines.phantom.training.train import TrainConfig, distillation
from tests.pipelines.phantom.test_core import street

CFG = PhantomConfig()


def samples_near(xyz: np.ndarray, passes: np.ndarray | None, centre_x: list[float]):
    """Labelled samples of 40 judged pillars round each x (a few metres of street each)."""
    pm = build_pillar_map(xyz, estimate_ground(xyz, CFG.ground_cell, CFG.ground_opening), CFG)
    judged = pm.pillars[pm.candidates()]
    centres = (judged + 0.5) * CFG.cell_size
    chosen = np.concatenate(
        [judged[np.argsort(np.abs(centres[:, 0] - x), kind="stable")[:40]] for x in centre_x]
    )
    labels = np.arange(len(chosen)) % 4
    lmap = LabelledPillars("street", xyz, chosen, labels, passes)
    return labelled_samples(lmap, CFG, 1, np.random.default_rng(0), context=False)


def test_fine_tuning_a_passes_network_keeps_its_second_channel() -> None:
    """train:phantom fine-tunes the promoted model, which for rotating scanners reads passes."""
    xyz = street(40_000)
    n = len(xyz)
    passes = np.arange(n) % 10
    samples = samples_near(xyz, passes, [float(np.median(xyz[:, 0]))])
    assert samples.x.shape[1] == 2
    base = PillarCNN(channels=(2, 2, 2), hidden=4, passes=True)
    result = finetune(samples, base, TrainConfig(epochs=1, batch=16), per_class=10)
    assert result.net.passes and result.net.conv1.in_channels == 2


def test_labels_in_few_blocks_still_pick_an_epoch() -> None:
    """An operator's first labels: two 10 m blocks (two folds), then one (pillars apart)."""
    xyz = street(40_000)
    lo, hi = np.percentile(xyz[:, 0], [10, 90])
    two = samples_near(xyz, None, [float(lo), float(hi)])
    config = TrainConfig(epochs=1, batch=16, block_size=10.0)
    assert epoch_split(two, config).folds == 2
    one = samples_near(xyz, None, [float(lo)])
    assert epoch_split(one, config).block_size == 0.0
    base = PillarCNN(channels=(2, 2, 2), hidden=4)
    for samples in (two, one):
        assert finetune(samples, base, config, per_class=10).net is not None


def test_classes_nobody_labelled_stay_out_of_the_loss() -> None:
    """Labels of ground and high objects only: the loss compares those two logits, so the
    phantom and short-object outputs get no gradient from being absent (weight decay off)."""
    xyz = street(40_000)
    samples = samples_near(xyz, None, [float(np.median(xyz[:, 0]))])
    two = samples.subset(np.flatnonzero(samples.y < 2))
    base = PillarCNN(channels=(2, 2, 2), hidden=4)
    config = TrainConfig(epochs=1, batch=16, weight_decay=0.0)
    result = finetune(two, base, config, per_class=10, distill=0.0)
    assert result.card["train_config"]["compared"] == [0, 1]
    before, after = base.state_dict(), result.net.state_dict()
    for name in ("fc2.weight", "fc2.bias"):
        change = after[name] - before[name]
        assert torch.equal(change[2:], torch.zeros_like(change[2:])), name
        assert change[:2].abs().sum() > 0, name


def test_a_class_with_a_handful_of_pillars_is_left_as_the_base_knew_it() -> None:
    xyz = street(40_000)
    samples = samples_near(xyz, None, [float(np.median(xyz[:, 0]))])
    rare = np.flatnonzero(samples.y == 3)[:3]
    few = samples.subset(np.concatenate([np.flatnonzero(samples.y < 2), rare]))
    assert labelled_pillars_per_class(few).tolist() == [10, 10, 0, 3]
    base = PillarCNN(channels=(2, 2, 2), hidden=4)
    config = TrainConfig(epochs=1, batch=16)
    result = finetune(few, base, config, per_class=10, min_class_labels=5)
    assert result.card["train_config"]["compared"] == [0, 1]
    assert sum(result.card["samples_per_class"].values()) == 20  # no phantom copies
    with pytest.raises(ValueError, match="fewer than two classes"):
        finetune(few, base, config, per_class=10, min_class_labels=11)


def test_fine_tuning_keeps_the_base_answers_by_distillation() -> None:
    """Learning without forgetting: the KL to the starting network's softened answers is 0 for
    the same logits and grows as the answers part; fine-tuning uses it by default."""
    same = torch.tensor([[2.0, 0.5, -1.0, 0.0]])
    assert distillation(same, same).item() == pytest.approx(0.0, abs=1e-7)
    apart = torch.tensor([[-1.0, 0.5, 2.0, 0.0]])
    assert distillation(apart, same).item() > distillation(same * 0.9, same).item() > 0
    xyz = street(40_000)
    samples = samples_near(xyz, None, [float(np.median(xyz[:, 0]))])
    base = PillarCNN(channels=(2, 2, 2), hidden=4)
    result = finetune(samples, base, TrainConfig(epochs=1, batch=16), per_class=10)
    assert result.card["train_config"]["distill"] == 1.0
