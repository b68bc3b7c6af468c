"""Phantom CNN training: pillar samples, class balance, k-fold training, model card, checkpoint."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from app.core.labels import PillarClass, Semantic
from app.pipelines.phantom.classify import window_tensor
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.model import load_model, save_model
from app.pipelines.phantom.network import CLASS_NAMES
from app.pipelines.phantom.training.dataset import (
    LabelledMap,
    Samples,
    balanced,
    concatenate,
    labelled_map_from_survey,
    labelled_pillars,
    pillar_samples,
    rotate_about_z,
    window_counts,
)
from app.pipelines.phantom.training.from_surveys import build_training_set, train_phantom_model
from app.pipelines.phantom.training.train import (
    TrainConfig,
    split_groups,
    stratified_folds,
    train,
)

GROUND, HIGH, SHORT, PHANTOM = (int(c) for c in PillarClass)


def surface_box(lo, hi, step, rng) -> np.ndarray:
    """Points on the four sides and the top of an axis-aligned box."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    xs, ys, zs = np.arange(x0, x1, step), np.arange(y0, y1, step), np.arange(z0, z1, step)
    parts = []
    for x in (x0, x1):
        gy, gz = np.meshgrid(ys, zs)
        parts.append(np.c_[np.full(gy.size, x), gy.ravel(), gz.ravel()])
    for y in (y0, y1):
        gx, gz = np.meshgrid(xs, zs)
        parts.append(np.c_[gx.ravel(), np.full(gx.size, y), gz.ravel()])
    gx, gy = np.meshgrid(xs, ys)
    parts.append(np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, z1)])
    pts = np.concatenate(parts)
    return pts + rng.normal(0, 0.005, pts.shape)


def synthetic_map(seed: int = 0) -> LabelledMap:
    """Ground plane, a parked car (box), a facade, and a moving car smeared sparsely along x."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(-10, 10, 0.07), np.arange(-10, 10, 0.07))
    ground = np.c_[gx.ravel(), gy.ravel(), rng.normal(0, 0.01, gx.size)]
    car = surface_box((2.0, 2.0, 0.3), (6.0, 3.8, 1.5), 0.05, rng)
    wall = surface_box((-8.0, 7.0, 0.0), (8.0, 7.4, 5.0), 0.05, rng)
    n = 4000
    moving = np.c_[rng.uniform(-8, 8, n), rng.uniform(-4.4, -3.0, n), rng.uniform(0.3, 1.5, n)]
    xyz = np.concatenate([ground, car, wall, moving]) + [1000.0, 2000.0, 50.0]
    semantic = np.concatenate(
        [
            np.full(len(ground), Semantic.ROAD),
            np.full(len(car), Semantic.CAR),
            np.full(len(wall), Semantic.BUILDING),
            np.full(n, Semantic.CAR),
        ]
    )
    flag = np.zeros(len(xyz), dtype=bool)
    flag[-n:] = True
    return LabelledMap(xyz=xyz, semantic=semantic, moving=flag, source="synthetic")


@pytest.fixture(scope="module")
def lmap() -> LabelledMap:
    return synthetic_map()


def test_pillar_samples_windows_and_labels(lmap):
    samples = pillar_samples(lmap, PhantomConfig(), np.random.default_rng(0), rotate=False)
    assert samples.x.shape[1:] == (1, 30, 24, 24)
    assert samples.x.dtype == np.uint8
    assert samples.y.dtype == np.int64
    assert len(samples.x) == len(samples.y) == len(samples.source)
    counts = samples.class_counts()
    assert all(counts[name] > 20 for name in CLASS_NAMES), counts
    info = samples.sources[0]
    assert info["name"] == "synthetic" and info["points"] == len(lmap)
    # nothing capped: every object pillar the CNN would judge is a sample, and plain road only
    # as many as the largest class (this flat map has no judged ground at all)
    assert info["judged_pillars"]["ground"] == 0
    assert counts["ground"] == max(counts[name] for name in CLASS_NAMES[1:])
    for name in CLASS_NAMES[1:]:
        assert counts[name] == info["judged_pillars"][name] <= info["pillars"][name]
    # the window of a phantom pillar holds the moving points around it, none at the car
    x, y = samples.batch(np.flatnonzero(samples.y == PHANTOM)[:5])
    assert x.dtype == torch.float32 and x.sum() > 0 and (y == PHANTOM).all()


def test_windows_equal_window_tensor_clipped_at_255(lmap):
    config = PhantomConfig()
    # 600 points in one voxel: its count is clipped to 255 in the uint8 storage
    xyz = np.concatenate([lmap.xyz, np.tile([[1000.03, 2000.03, 51.05]], (600, 1))])
    pm, _ = labelled_pillars(
        LabelledMap(
            xyz, np.r_[lmap.semantic, np.full(600, 10)], np.r_[lmap.moving, [False] * 600], "x"
        ),
        config,
    )
    rng = np.random.default_rng(1)
    pick = pm.pillars[rng.choice(len(pm.pillars), 300, replace=False)]
    hot = np.floor(np.array([1000.03, 2000.03]) / config.cell_size).astype(np.int64)
    pick = np.concatenate([pick, hot[None]])
    got = window_counts(pm, pick, batch=64)
    want = window_tensor(pm, pick).numpy()
    assert want.max() > 255
    np.testing.assert_array_equal(got, np.minimum(want, 255).astype(np.uint8))


def test_rotation_changes_windows_keeps_label_counts(lmap):
    config = PhantomConfig()
    plain = pillar_samples(lmap, config, np.random.default_rng(0), rotate=False)
    turned = pillar_samples(lmap, config, np.random.default_rng(3), rotate=True)
    angle = turned.sources[0]["rotation_deg"] % 90
    assert 10 < angle < 80  # seeded: a real turn, not a quarter turn
    a, b = plain.class_counts(), turned.class_counts()
    for name in CLASS_NAMES:
        assert abs(a[name] - b[name]) <= 0.4 * a[name] + 5, (name, a, b)

    # the moving line runs along x unrotated; the mean phantom window's footprint turns with it
    def footprint(s: Samples) -> np.ndarray:
        img = s.x[s.y == PHANTOM].astype(np.float64).sum(axis=(0, 1, 2))
        return img / img.sum()

    fa, fb = footprint(plain), footprint(turned)
    assert np.corrcoef(fa.ravel(), fb.ravel())[0, 1] < 0.9
    # the point cloud itself: rotated about its centroid, distances kept
    rotated = rotate_about_z(lmap.xyz[:1000], 0.7)
    np.testing.assert_allclose(rotated.mean(axis=0), lmap.xyz[:1000].mean(axis=0), atol=1e-9)
    d0 = np.linalg.norm(lmap.xyz[1] - lmap.xyz[500])
    assert np.isclose(np.linalg.norm(rotated[1] - rotated[500]), d0)


def test_max_per_class_caps(lmap):
    samples = pillar_samples(lmap, PhantomConfig(), np.random.default_rng(0), max_per_class=25)
    assert max(samples.class_counts().values()) == 25
    only = pillar_samples(
        lmap, PhantomConfig(), np.random.default_rng(0), max_per_class={0: 0, 1: 0, 2: 0, 3: 7}
    )
    assert only.class_counts() == {"ground": 0, "high object": 0, "short object": 0, "phantom": 7}


def _toy_samples(per_class: int, seed: int = 0) -> Samples:
    """Learnable windows: class c has a dense band of counts at heights 7c..7c+5."""
    rng = np.random.default_rng(seed)
    n = per_class * 4
    y = np.repeat(np.arange(4), per_class)
    x = rng.poisson(0.3, (n, 1, 30, 24, 24)).astype(np.uint8)
    for c in range(4):
        band = x[y == c, :, 7 * c : 7 * c + 5, 6:18, 6:18]
        x[y == c, :, 7 * c : 7 * c + 5, 6:18, 6:18] = band + rng.poisson(4, band.shape).astype(
            np.uint8
        )
    xy = np.c_[np.arange(n) * 20.0, np.zeros(n)]  # a 10 m block each
    return Samples(x=x, y=y, source=np.full(n, "toy"), xy=xy, sources=[{"name": "toy"}])


def test_balanced_gives_per_class_each():
    rng = np.random.default_rng(0)
    s = _toy_samples(10)
    s = s.subset(np.r_[np.flatnonzero(s.y != 3), np.flatnonzero(s.y == 3)[:4]])  # 4 phantoms
    out = balanced(s, 8, rng)
    assert out.class_counts() == dict.fromkeys(CLASS_NAMES, 8)
    # the scarce class: each of its samples at least once, the rest drawn again (same group)
    phantom_groups = out.group[out.y == 3]
    assert set(phantom_groups) == set(s.group[s.y == 3])
    # the rich classes: no repeats
    assert len(np.unique(out.group[out.y == 0])) == 8
    assert not np.array_equal(out.y, np.sort(out.y))  # shuffled
    with pytest.raises(ValueError, match="phantom"):
        balanced(s.subset(np.flatnonzero(s.y != 3)), 8, rng)


def test_stratified_folds_keep_groups_together():
    y = np.repeat(np.arange(4), 50)
    group = np.arange(200) // 2  # pairs of copies
    fold = stratified_folds(y, group, 5, np.random.default_rng(0))
    for c in range(4):
        assert np.bincount(fold[y == c], minlength=5).tolist() == [10] * 5
    assert (fold[0::2] == fold[1::2]).all()


def test_rotated_samples_keep_their_unrotated_location(lmap):
    turned = pillar_samples(lmap, PhantomConfig(), np.random.default_rng(3), rotate=True)
    xy = turned.xy[turned.y == PHANTOM] - [1000.0, 2000.0]
    # the moving points fill x -8..8, y -4.4..-3 in the unrotated map (plus a pillar's reach)
    assert (xy[:, 0] > -8.3).all() and (xy[:, 0] < 8.3).all()
    assert (xy[:, 1] > -4.7).all() and (xy[:, 1] < -2.7).all()


def test_blocked_split_keeps_map_blocks_whole(lmap):
    samples = pillar_samples(lmap, PhantomConfig(), np.random.default_rng(0))
    rotated = pillar_samples(lmap, PhantomConfig(), np.random.default_rng(1))
    both = concatenate([samples, rotated])
    groups = split_groups(both, 4.0)
    fold = stratified_folds(both.y, groups, 5, np.random.default_rng(0))
    block = np.floor(both.xy / 4.0).astype(np.int64)
    for key in np.unique(block, axis=0):
        inside = (block == key).all(axis=1)
        assert len(np.unique(fold[inside])) == 1  # both rotations of a block on one side
    assert (np.bincount(fold, minlength=5) > 0).all()
    assert (split_groups(both, 0.0) == both.group).all()


def test_train_reduces_loss_and_writes_card(tmp_path):
    samples = _toy_samples(200)
    config = TrainConfig(epochs=2, batch=32, threads=2)  # lr0 0.05, the default
    result = train(samples, config)
    losses = [h["train_loss"] for h in result.history]
    assert len(losses) == 2 and losses[1] < losses[0] < 1.5
    for key in (
        "training_sources",
        "class_mapping",
        "classes",
        "samples_per_class",
        "train_config",
        "history",
        "best_epoch",
        "validation",
        "training_seconds",
        "cross_validation",
    ):
        assert key in result.card, key
    assert result.card["samples_per_class"] == dict.fromkeys(CLASS_NAMES, 200)
    assert result.card["cross_validation"]["per_fold"][0]["validation_samples"] == 160
    validation = result.card["validation"]
    assert set(validation["classes"]) == set(CLASS_NAMES)
    assert validation["macro"]["f1"] > 90.0
    assert "majority" in result.card["class_mapping"]
    assert result.card["history"][1]["lr"] == pytest.approx(0.025)  # lr0 / (e + 1)

    path = save_model(tmp_path / "phantom.pt", result.net, result.card)
    net, card = load_model(path)
    x, _ = samples.batch(np.arange(16))
    result.net.eval()
    with torch.no_grad():
        assert torch.equal(net(x), result.net(x))
    assert card["best_epoch"] == result.card["best_epoch"]


def test_time_limit_stops_between_epochs():
    config = TrainConfig(epochs=5, batch=32, folds=4, threads=2, time_limit=1e-6)
    result = train(_toy_samples(20), config)
    assert len(result.history) == 1
    assert result.card["cross_validation"]["per_fold"][0]["epochs_run"] == 1


def test_train_phantom_model_end_to_end(tmp_path):
    out = tmp_path / "models" / "phantom_cnn.pt"
    config = TrainConfig(per_class=40, epochs=1, batch=32, rotations=2, threads=2)
    cache = tmp_path / "cache"
    card = train_phantom_model(out, [0], [], config, sim_length=20.0, cache_dir=cache)
    assert out.is_file() and out.with_suffix(".card.json").is_file()
    assert card["samples_per_class"] == dict.fromkeys(CLASS_NAMES, 40)
    (source,) = card["training_sources"]
    assert source["format"] == "sim" and source["points"] > 0
    assert len(source["rotations_deg"]) in (1, 2)
    assert (cache / "sim-urban-20m-profile-seed0" / "ground_truth" / "simulation.json").is_file()
    net, loaded = load_model(out)
    assert loaded["samples_per_class"] == card["samples_per_class"]
    # map priors for the pipeline: frequencies of the judged pillars of the training map
    judged = np.array([source["judged_pillars"][name] for name in CLASS_NAMES], dtype=float)
    assert np.allclose(loaded["class_priors"], np.maximum(judged / judged.sum(), 1e-3), atol=2e-3)


def test_semantickitti_samples(real_data):
    from app.io import open_survey

    sequence = real_data / "semantickitti" / "sequences" / "05"
    if not sequence.is_dir():
        pytest.skip(f"{sequence} is missing")
    lmap = labelled_map_from_survey(open_survey(sequence, "semantickitti"))
    assert len(lmap) == len(lmap.semantic) == len(lmap.moving) and lmap.moving.any()
    samples = build_training_set(
        [], [sequence], TrainConfig(per_class=30, rotations=2), np.random.default_rng(0)
    )
    assert samples.class_counts() == dict.fromkeys(CLASS_NAMES, 30)
    assert samples.sources[0]["format"] == "semantickitti"
    assert samples.sources[0]["pillars"]["phantom"] > 0


def test_context_samples_and_training(lmap, tmp_path):
    samples = pillar_samples(lmap, PhantomConfig(), np.random.default_rng(0), context=True)
    assert samples.bands.shape == (len(samples), 6, 31, 31) and samples.bands.dtype == np.uint8
    both = concatenate([samples, samples.subset(np.arange(10))])
    assert len(both.bands) == len(samples) + 10
    assert torch.equal(both.context_batch([len(samples)]), samples.context_batch([0]))
    config = TrainConfig(epochs=2, batch=32, folds=4, threads=2, context=4, block_size=0)
    result = train(samples, config)
    path = save_model(tmp_path / "context.pt", result.net, result.card)
    net, card = load_model(path)
    assert card["network"]["context"] == 4 and net.context_net is not None
    x, _ = samples.batch(np.arange(8))
    bands = samples.context_batch(np.arange(8))
    with torch.no_grad():
        assert torch.equal(net(x, bands), result.net.eval()(x, bands))
