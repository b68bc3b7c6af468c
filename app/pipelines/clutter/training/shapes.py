"""Training the vehicle shape classifier (`shapes.py`) on the simulator's labelled objects.

Each simulated street (rotating scanners drawn from the seed: 32 or 64 beams, mountings, noise)
is clustered per frame as the pipeline clusters it; an object-sized, trackable cluster is a
vehicle when at least `PURE` of its scored points are (SemanticKITTI car, bus, tram, truck,
other vehicle, parked or moving), other when at most 1 - `PURE` are; mixed ones teach nothing.
Streets cycle through presets and situations (`SCENES`, or a cycle the caller names), so
parked cars, site machines, trailers and vans stand among stalls, kiosks, hedges, tree trunks,
poles and people. `street_samples` reads any survey with reference labels, so the same clusters
are measured on real SemanticKITTI (`bench/clutter_shapes.py`) and can be learnt from there.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import nn

from app.core.errors import ConfigError
from app.core.settings import get_settings
from app.io import open_survey
from app.io.survey import Survey
from app.pipelines.clutter.clusters import frame_clusters
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.expansion import cluster_sizes
from app.pipelines.clutter.shapes import (
    FEATURES,
    MIRRORS,
    SHAPE_POINTS,
    ShapeInputs,
    ShapeNet,
    VehicleShapes,
    mirror_of,
    shape_inputs,
)

VEHICLE_IDS = np.array([10, 13, 16, 18, 20, 252, 256, 257, 258, 259])
# the shipped model's cycle of scenes (seed % len); `--scenes` trains on another
SCENES = ("urban", "mixed", "shadow", "market", "walkers", "receding", "approaching")
PURE = 0.7
LENGTH = 40.0  # metres per simulated street
FRAME_STEP = 2  # every second frame: neighbouring frames see the same objects
THRESHOLD = 0.5  # P(vehicle) the validation scores are given at
SAMPLES_SUFFIX = ".shape-samples-v2.npz"  # beside each cached street (summary, points, classes)
JITTER = 0.02  # metres of noise added to the training points


def scene_cycle(text: str) -> tuple[str, ...]:
    """ "urban,shadow,parked_rows" -> the scenes; ConfigError naming `--scenes` for an unknown
    one."""
    from app.simulate.survey import SimulationConfig

    known = SimulationConfig.model_fields["scene"].annotation.__args__
    cycle = tuple(name.strip() for name in text.split(",") if name.strip())
    unknown = [name for name in cycle if name not in known]
    if not cycle or unknown:
        raise ConfigError(
            "--scenes", f"unknown scenes {unknown or text!r}; known: {', '.join(known)}"
        )
    return cycle


def simulated_street(
    seed: int,
    cache: Path | None = None,
    scenes: tuple[str, ...] = SCENES,
    vegetation: bool = False,
) -> Path:
    """A cached simulated street of `seed`, its scene `scenes[seed % len(scenes)]`, no camera
    (shapes need none), with hedges and bushes where `vegetation`."""
    from app.simulate.survey import SimulationConfig, simulate

    cache = cache or get_settings().cache_dir / "clutter-shapes"
    scene = scenes[seed % len(scenes)]
    folder = cache / f"{scene}-{LENGTH:g}m-seed{seed}{'-vegetation' if vegetation else ''}"
    if not folder.is_dir():
        config = SimulationConfig(
            scene=scene, length=LENGTH, seed=seed, scanner="hdl64", camera=False,
            vary_scanner=True, write_map=False, vegetation=vegetation,
        )  # fmt: skip
        simulate(config, folder)
    return folder


def street_samples(
    survey: Survey | Path, config: ClutterConfig | None = None, step: int = FRAME_STEP
) -> tuple[ShapeInputs, np.ndarray, np.ndarray]:
    """(inputs of M clusters, label (M,) 1 vehicle / 0 other, the SemanticKITTI class most of
    each one's scored points hold (M,)) of one street's trackable clusters, every `step`-th
    frame. A path is a simulated street."""
    cfg = config or ClutterConfig()
    survey = open_survey(survey, "sim") if isinstance(survey, Path) else survey
    features, clouds, labels, classes = [], [], [], []
    for index, frame in enumerate(list(survey.frames)[::step]):
        xyz = frame.points().xyz
        semantic = frame.reference_labels()["semantic"] & 0xFFFF
        clusters = frame_clusters(
            xyz, cfg.cluster_voxel, cfg.ground_cell, cfg.ground_tolerance, cfg.max_range
        )
        count = clusters.count
        if count == 0:
            continue
        sizes = cluster_sizes(xyz, clusters)
        inside = clusters.label >= 0
        points = np.bincount(clusters.label[inside], minlength=count)
        scored = inside & (semantic > 1)
        total = np.bincount(clusters.label[scored], minlength=count)
        vehicle = np.bincount(
            clusters.label[scored & np.isin(semantic, VEHICLE_IDS)], minlength=count
        )
        trackable = sizes.within(cfg.max_object_extent, cfg.max_object_height) & (
            points >= cfg.min_track_points
        )
        share = vehicle / np.maximum(total, 1)
        keep = trackable & (total > 0) & ((share >= PURE) | (share <= 1.0 - PURE))
        if not keep.any():
            continue
        inputs = shape_inputs(xyz, clusters.label, clusters.above_ground, keep, index)
        features.append(inputs.features[keep])
        clouds.append(inputs.points[keep])
        labels.append((share[keep] >= PURE).astype(np.int8))
        classes.append(_majority_class(clusters.label[scored], semantic[scored], count)[keep])
    frames = zip(features, clouds, labels, classes, strict=True)
    return _joined([(ShapeInputs(f, c), y, k) for f, c, y, k in frames])


def _majority_class(label: np.ndarray, semantic: np.ndarray, count: int) -> np.ndarray:
    """(count,) per cluster the semantic class most of its points hold (0 for none)."""
    out = np.zeros(count, np.uint16)
    if len(label) == 0:
        return out
    pairs, votes = np.unique(
        label.astype(np.int64) << 16 | semantic.astype(np.int64), return_counts=True
    )
    cluster, cls = pairs >> 16, pairs & 0xFFFF
    order = np.lexsort((votes, cluster))  # per cluster, the most votes last
    last = np.r_[cluster[order][1:] != cluster[order][:-1], True]
    out[cluster[order][last]] = cls[order][last]
    return out


def samples(
    seeds: list[int],
    cache: Path | None = None,
    scenes: tuple[str, ...] = SCENES,
    vegetation: bool = False,
) -> tuple[ShapeInputs, np.ndarray, np.ndarray]:
    """The samples of several streets (each cached next to its street): inputs, labels,
    classes as `street_samples`."""
    cache = cache or get_settings().cache_dir / "clutter-shapes"
    xs, ps, ys, cs = [], [], [], []
    for seed in seeds:
        street = simulated_street(seed, cache, scenes, vegetation)
        target = street.with_name(street.name + SAMPLES_SUFFIX)
        if not target.is_file():
            inputs, y, classes = street_samples(street)
            partial = target.with_suffix(".partial.npz")
            np.savez_compressed(
                partial, features=inputs.features, points=inputs.points.astype(np.float16),
                labels=y, classes=classes,
            )  # fmt: skip
            os.replace(partial, target)
        with np.load(target) as z:
            xs.append(z["features"])
            ps.append(z["points"].astype(np.float32))
            ys.append(z["labels"])
            cs.append(z["classes"])
    inputs = ShapeInputs(np.concatenate(xs), np.concatenate(ps))
    return inputs, np.concatenate(ys), np.concatenate(cs)


def labelled_samples(surveys: list[Survey]) -> tuple[ShapeInputs, np.ndarray, np.ndarray]:
    """The samples of real surveys with SemanticKITTI reference labels (every frame: a real
    sequence is short and every view of an object is worth having)."""
    return _joined([street_samples(survey, step=1) for survey in surveys])


def _joined(
    parts: list[tuple[ShapeInputs, np.ndarray, np.ndarray]],
) -> tuple[ShapeInputs, np.ndarray, np.ndarray]:
    """Sample sets as one; none gives an empty set."""
    if not parts:
        empty = ShapeInputs(
            np.zeros((0, len(FEATURES)), np.float32), np.zeros((0, SHAPE_POINTS, 3), np.float32)
        )
        return empty, np.zeros(0, np.int8), np.zeros(0, np.uint16)
    inputs = ShapeInputs(
        np.concatenate([p[0].features for p in parts]), np.concatenate([p[0].points for p in parts])
    )
    return inputs, np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts])


def with_real(
    simulated: tuple[ShapeInputs, np.ndarray, np.ndarray],
    real: tuple[ShapeInputs, np.ndarray, np.ndarray],
    real_weight: float,
) -> tuple[ShapeInputs, np.ndarray, np.ndarray]:
    """Simulated and real samples as one training set: (inputs, labels, each sample's weight,
    1 for a simulated cluster and `real_weight` for a real one)."""
    inputs, y, _ = _joined([simulated, real])
    weight = np.r_[np.ones(len(simulated[1])), np.full(len(real[1]), real_weight)]
    return inputs, y, weight.astype(np.float32)


def train_shapes(
    inputs: ShapeInputs,
    y: np.ndarray,
    epochs: int = 30,
    seed: int = 0,
    card: dict | None = None,
    weight: np.ndarray | None = None,
) -> VehicleShapes:
    """Fit the network (class-balanced binary cross-entropy, each sample's loss times its
    `weight`, Adam, the rate a tenth for the last third) on standardised features and the
    clusters' points, each sample in a random mirror image with `JITTER` of noise. A larger
    weight on a few real clusters lets them count beside thousands of simulated ones."""
    torch.manual_seed(seed)
    x = inputs.features
    mean = x.mean(axis=0).astype(np.float32)
    std = np.maximum(x.std(axis=0), 1e-3).astype(np.float32)
    summary = torch.from_numpy(((x - mean) / std).astype(np.float32))
    points = torch.from_numpy(inputs.points.astype(np.float32))
    target = torch.from_numpy(y.astype(np.float32))
    sample_weight = torch.ones(len(y)) if weight is None else torch.from_numpy(weight).float()
    positives = max(float((target * sample_weight).sum()), 1.0)
    balance = torch.tensor((float(sample_weight.sum()) - positives) / positives)
    net = ShapeNet(x.shape[1])
    loss_fn = nn.BCEWithLogitsLoss(pos_weight=balance, reduction="none")
    optimiser = torch.optim.Adam(net.parameters(), lr=2e-3, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.MultiStepLR(optimiser, [max(1, 2 * epochs // 3)], 0.1)
    order = torch.Generator().manual_seed(seed)
    mirrors = torch.stack([mirror_of(m) for m in MIRRORS])
    for _ in range(epochs):
        for batch in torch.randperm(len(target), generator=order).split(256):
            flip = mirrors[torch.randint(len(MIRRORS), (len(batch),), generator=order)]
            noise = JITTER * torch.randn(points[batch].shape, generator=order)
            optimiser.zero_grad()
            logits = net(summary[batch], points[batch] * flip[:, None, :] + noise)
            w = sample_weight[batch]
            loss = (loss_fn(logits, target[batch]) * w).sum() / w.sum()
            loss.backward()
            optimiser.step()
        schedule.step()
    return VehicleShapes(net.eval(), mean, std, dict(card or {}))


def scores(model: VehicleShapes, inputs: ShapeInputs, y: np.ndarray, threshold: float) -> dict:
    """Precision and recall of `vehicle` at `threshold`, per cent."""
    said = model.probability(inputs) >= threshold
    truth = y.astype(bool)
    hits = int((said & truth).sum())
    return {
        "samples": int(len(y)),
        "vehicles": int(truth.sum()),
        "precision": round(100.0 * hits / max(int(said.sum()), 1), 2),
        "recall": round(100.0 * hits / max(int(truth.sum()), 1), 2),
    }
