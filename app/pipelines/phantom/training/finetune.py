"""Fine-tuning the phantom CNN on pillars people labelled (the paper's own training data were
hand-labelled pillars): the labels come as pillar indices on the world grid of `build_pillar_map`
(floor(x / s_c), floor(y / s_c)), the map as world points.

- Samples: the map is rotated about the vertical axis through its centroid (the paper's
  augmentation), the labelled pillar centres with it, and each centre is looked up in the
  rotated pillar map; pillars with no points in the 3 m layer give no sample. The first copy is
  unrotated.
- Validation on labels the network did not train on: map blocks (`block_size` metres, whole
  blocks only, so neighbouring pillars that share most of their window never straddle the
  split; `app.metrics.splits`) are held out at random; both the new and the base network are
  scored on them, so a new version is promoted only when it is not worse than the one it
  would replace.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from app.core.progress import Progress
from app.metrics.classification import Scores
from app.pipelines.phantom.classify import band_tensor
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.network import PillarCNN
from app.pipelines.phantom.pillars import build_pillar_map, phantom_ground
from app.pipelines.phantom.training.dataset import (
    Samples,
    balanced,
    concatenate,
    rotate_about_z,
    window_counts,
)
from app.pipelines.phantom.training.train import (
    TrainConfig,
    TrainResult,
    evaluate_net,
    pillar_scores,
    split_groups,
    train,
)


@dataclass
class LabelledPillars:
    """Human pillar labels of one map: world-grid pillar indices and classes."""

    name: str
    xyz: np.ndarray  # (N, 3) float64 world points of the map
    pillars: np.ndarray  # (L, 2) int64 (ix, iy) on the s_c grid
    labels: np.ndarray  # (L,) int64 class 0..3
    passes: np.ndarray | None = None  # (N,) scanner pass of each point, for a passes network


def _lookup(found: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Index of each wanted (ix, iy) row in `found` (sorted lexicographically by the map), -1
    where absent."""
    key_found = found[:, 0] * (1 << 32) + found[:, 1]
    key_wanted = wanted[:, 0] * (1 << 32) + wanted[:, 1]
    order = np.argsort(key_found, kind="stable")
    pos = np.searchsorted(key_found[order], key_wanted)
    pos = np.clip(pos, 0, max(len(order) - 1, 0))
    hit = len(order) > 0
    index = np.where(hit & (key_found[order][pos] == key_wanted), order[pos], -1)
    return index.astype(np.int64)


def labelled_samples(
    lmap: LabelledPillars,
    config: PhantomConfig,
    rotations: int,
    rng: np.random.Generator,
    context: bool,
) -> Samples:
    """Samples of the labelled pillars of one map: an unrotated copy, then `rotations - 1`
    random rotations."""
    cs = config.cell_size
    centres = np.zeros((len(lmap.pillars), 3))
    centres[:, :2] = (lmap.pillars + 0.5) * cs
    pivot = lmap.xyz.mean(axis=0) if len(lmap.xyz) else np.zeros(3)
    parts = []
    for r in range(rotations):
        angle = 0.0 if r == 0 else float(rng.uniform(0.0, 2.0 * np.pi))
        xyz = rotate_about_z(lmap.xyz, angle, pivot) if angle else lmap.xyz
        turned = rotate_about_z(centres, angle, pivot) if angle else centres
        ground = phantom_ground(xyz, config)
        pm = build_pillar_map(xyz, ground, config, lmap.passes)
        index = _lookup(pm.pillars, np.floor(turned[:, :2] / cs).astype(np.int64))
        keep = index >= 0
        chosen = pm.pillars[index[keep]]
        parts.append(
            Samples(
                x=window_counts(pm, chosen),
                bands=window_counts(pm, chosen, cut=band_tensor) if context else None,
                y=lmap.labels[keep],
                source=np.full(int(keep.sum()), lmap.name),
                xy=centres[keep, :2],
                group=np.flatnonzero(keep),
                sources=[{"name": lmap.name, "labels": int(len(keep)), "kept": int(keep.sum())}],
            )
        )
    samples = concatenate(parts)
    samples.sources = parts[0].sources
    return samples


@torch.no_grad()
def score(net: PillarCNN, samples: Samples) -> Scores:
    """Pillar classification scores of a network on samples (raw argmax, no priors)."""
    _, predicted = evaluate_net(net, samples, np.arange(len(samples)), 256)
    return pillar_scores(samples.y, predicted)


def labelled_pillars_per_class(samples: Samples) -> np.ndarray:
    """(4,) distinct labelled pillars per class (rotated copies of one pillar count once)."""
    _, source = np.unique(samples.source, return_inverse=True)
    keys = np.unique(np.c_[samples.y, source.ravel(), samples.group], axis=0)
    return np.bincount(keys[:, 0], minlength=4)[:4]


def finetune(
    train_samples: Samples,
    base: PillarCNN,
    config: TrainConfig,
    per_class: int,
    progress: Progress | None = None,
    min_class_labels: int = 1,
    distill: float = 1.0,
) -> TrainResult:
    """Train from the base network's weights on class-balanced copies of the labelled samples.
    Classes nobody labelled, or fewer than `min_class_labels` pillars of, are left out of the
    samples and of the loss (which compares the kept classes' logits only), as the base knew
    them: an operator's first labels are often ground and buildings alone, and a loss over all
    four classes teaches the network that phantoms never occur; a handful of phantom pillars
    copied up to the largest class's size teaches it those pillars, not the class. And the
    base network's answers on the training windows are kept (`distill`, learning without
    forgetting), since new labels reshape the features every class shares (measured in the
    labelling loop: phantom recall 0 on the held-out sequences without these)."""
    rng = np.random.default_rng(config.seed)
    kept = np.flatnonzero(labelled_pillars_per_class(train_samples) >= min_class_labels)
    if len(kept) < 2:
        raise ValueError(
            f"fewer than two classes with {min_class_labels} labelled pillars to fine-tune on"
        )
    train_samples = train_samples.subset(np.flatnonzero(np.isin(train_samples.y, kept)))
    present = np.bincount(train_samples.y, minlength=4)
    want = int(min(max(present.max(), 1), per_class))
    pool = balanced(train_samples, want, rng, allow_missing=True)
    labelled = kept.tolist()
    shaped = epoch_split(pool, config).model_copy(
        update={
            "channels": tuple(base.channels),
            "hidden": base.hidden,
            "context": base.context,
            "passes": base.passes,
            "compared": labelled if len(labelled) < 4 else None,  # two or more (above)
            "distill": distill,
        }
    )
    return train(pool, shaped, progress, initial_state=base.state_dict())


def epoch_split(pool: Samples, config: TrainConfig) -> TrainConfig:
    """The split fine-tuning picks its best epoch on. An operator's first labels lie in a few
    map blocks, too few for the usual five folds: as many folds as blocks (at least two), or in
    one block, pillars apart (neighbours then share windows across this split; the held-out
    blocks that decide promotion stay whole)."""
    blocks = len(np.unique(split_groups(pool, config.block_size)))
    if blocks >= config.folds:
        return config
    if blocks >= 2:
        return config.model_copy(
            update={"folds": blocks, "folds_to_run": min(config.folds_to_run, blocks)}
        )
    return config.model_copy(update={"block_size": 0.0})
