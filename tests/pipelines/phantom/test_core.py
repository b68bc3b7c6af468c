"""Phantom pipeline core: ground model, pillar voxels, dense == per-window, refinement, labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from app.geometry.ground import estimate_ground
from app.pipelines.phantom.classify import (
    classify_dense,
    classify_windows,
    network_inputs,
    window_tensor,
)
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.network import PillarCNN
from app.pipelines.phantom.pillars import build_pillar_map
from app.pipelines.phantom.point_labels import point_labels
from app.pipelines.phantom.refine import refine

CFG = PhantomConfig()


def street(n: int = 60_000, seed: int = 0, slope: float = 0.05) -> np.ndarray:
    """A sloped ground plane with a 'building' wall and a 'car' box on it."""
    rng = np.random.default_rng(seed)
    g = np.column_stack([rng.uniform(0, 30, n), rng.uniform(-8, 8, n), np.zeros(n)])
    wall = np.column_stack(
        [rng.uniform(0, 30, n // 4), np.full(n // 4, 7.5), rng.uniform(0, 8, n // 4)]
    )
    car = np.column_stack(
        [
            rng.uniform(10, 14.5, n // 6),
            rng.uniform(-3, -1.2, n // 6),
            rng.uniform(0.3, 1.5, n // 6),
        ]
    )
    xyz = np.concatenate([g, wall, car])
    xyz[:, 2] += slope * xyz[:, 0] + 100.0
    return xyz


def random_net(seed: int = 0, context: int = 0) -> PillarCNN:
    torch.manual_seed(seed)
    net = PillarCNN(context=context)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 0.3)
    return net.eval()


def test_ground_follows_a_slope_under_objects() -> None:
    xyz = street()
    ground = estimate_ground(xyz, CFG.ground_cell, CFG.ground_opening)
    probe = np.array([[5.0, 0.0], [12.0, -2.0], [25.0, 6.0]])  # road, under the car, by the wall
    expected = 100.0 + 0.05 * probe[:, 0]
    assert np.abs(ground.height(probe) - expected).max() < 0.1


def test_pillar_voxels_count_every_point_in_the_layer() -> None:
    xyz = street()
    pm = build_pillar_map(xyz, estimate_ground(xyz), CFG)
    in_layer = pm.point_pillar >= 0
    assert pm.counts.sum() == in_layer.sum()
    assert (pm.height[in_layer] < CFG.pillar_height).all()
    assert not in_layer[xyz[:, 2] - (100 + 0.05 * xyz[:, 0]) > 3.2].any()  # wall above 3 m
    # a point's pillar is the floor of its coordinates over 0.2 m
    i = np.flatnonzero(in_layer)[:1000]
    assert np.array_equal(pm.pillars[pm.point_pillar[i]], np.floor(xyz[i, :2] / 0.2).astype(int))
    block = pm.dense_block(int(pm.vx.min()), int(pm.vy.min()), 400, 200)
    assert block.sum() == pm.counts.sum() and block.shape == (30, 400, 200)


def test_window_holds_the_neighbourhood() -> None:
    xyz = np.array([[0.05, 0.05, 0.05], [0.05 + 5 * 0.2, 0.05, 1.05], [2.0, 2.0, 0.5]])
    pm = build_pillar_map(np.concatenate([xyz, [[0.0, 0.0, 0.0]]]), estimate_ground(xyz), CFG)
    x = window_tensor(pm, np.array([[0, 0]]))
    assert x.shape == (1, 1, 30, 24, 24)
    # centre pillar (0, 0): voxels 10..11 of the 22-wide window, +1 context voxel
    assert x[0, 0, :, 11, 11].sum() >= 1
    assert x[0, 0, 10, 21, 11] == 1  # the point 5 pillars further in x, 1.05 m up
    assert x.sum() == 3  # (2, 2) lies 10 pillars away: outside the window


@pytest.fixture(scope="module")
def per_window() -> tuple:
    xyz = street(30_000, seed=1)
    pm = build_pillar_map(xyz, estimate_ground(xyz), CFG)
    net = random_net()
    return pm, net, classify_windows(net, pm, batch=256)


@pytest.mark.parametrize("tile", [16, 40])
def test_dense_equals_per_window(per_window: tuple, tile: int) -> None:
    pm, net, ref = per_window
    dense = classify_dense(net, pm, tile=tile)
    assert np.abs(ref - dense).max() < 1e-4
    assert (ref.argmax(1) == dense.argmax(1)).mean() >= 0.999


def test_refinement_takes_the_local_majority() -> None:
    pillars = np.array([[x, y] for x in range(7) for y in range(7)])
    labels = np.full(len(pillars), 2, dtype=np.uint8)  # a patch of short objects
    labels[24] = 3  # one phantom in the middle
    labels[0] = 0  # ground stays ground
    refined = refine(pillars, labels, 5)
    assert refined[24] == 2 and refined[0] == 0
    lone = refine(np.array([[0, 0], [10, 10]]), np.array([3, 1], dtype=np.uint8), 5)
    assert lone.tolist() == [3, 1]  # nothing else around: keeps its own label


def test_points_at_ground_level_stay_ground() -> None:
    xyz = street()
    pm = build_pillar_map(xyz, estimate_ground(xyz), CFG)
    labels = point_labels(pm, np.full(len(pm.pillars), 3, dtype=np.uint8))
    at_ground = np.abs(pm.height) < 0.05
    assert (labels[at_ground] == 0).all()
    assert (labels[(pm.height > 0.3) & (pm.height < 2.9)] == 3).all()


def test_only_pillars_with_object_points_go_to_the_cnn() -> None:
    xyz = street()
    pm = build_pillar_map(xyz, estimate_ground(xyz), CFG)
    which = pm.candidates()
    above = pm.point_pillar[(pm.point_pillar >= 0) & (pm.height > CFG.ground_tolerance)]
    counts = np.bincount(above, minlength=len(pm.pillars))
    assert np.array_equal(which, np.flatnonzero(counts >= CFG.min_object_points))
    # the car footprint (10..14.5 x -3..-1.2) is judged, the open road beside it is not
    centres = (pm.pillars[which] + 0.5) * CFG.cell_size
    on_car = (centres[:, 0] > 10.2) & (centres[:, 0] < 14.3) & (centres[:, 1] > -2.8)
    on_car &= centres[:, 1] < -1.4
    assert on_car.sum() > 0.9 * (4.1 / 0.2) * (1.4 / 0.2)
    road = (pm.pillars[:, 1] * 0.2 > -7) & (pm.pillars[:, 1] * 0.2 < -4)
    assert not np.isin(np.flatnonzero(road), which).any()


def test_classifying_a_subset_gives_the_same_rows(per_window: tuple) -> None:
    pm, net, ref = per_window
    which = pm.candidates()
    assert 0 < len(which) < len(pm.pillars)
    dense = classify_dense(net, pm, tile=16, which=which)
    windows = classify_windows(net, pm, batch=256, which=which)
    assert np.abs(dense - ref[which]).max() < 1e-4
    assert np.abs(windows - ref[which]).max() < 1e-5


def test_context_branch_dense_equals_per_window(per_window: tuple) -> None:
    pm, _, _ = per_window
    net = random_net(seed=3, context=8)
    which = pm.candidates()
    windows = classify_windows(net, pm, batch=128, which=which)
    for tile in (16, 40):
        dense = classify_dense(net, pm, tile=tile, which=which)
        assert np.abs(windows - dense).max() < 1e-4
    # the branch reads 6.2 m around the pillar: a car 3 m away changes the output
    far = pm.pillars[which][:1]
    x, bands = network_inputs(net, pm, far)
    assert bands.shape == (1, 6, 31, 31) and bands.sum() > x.sum()
    with pytest.raises(ValueError, match="context branch"):
        net(x)


def test_band_counts_sum_the_pillar_columns() -> None:
    xyz = street()
    pm = build_pillar_map(xyz, estimate_ground(xyz), CFG)
    px, py = int(pm.pillars[:, 0].min()), int(pm.pillars[:, 1].min())
    nx, ny = np.ptp(pm.pillars, axis=0) + 1
    bands = pm.band_block(px, py, int(nx), int(ny))
    assert bands.shape == (6, nx, ny) and bands.sum() == pm.counts.sum()
    per_pillar = np.bincount(pm.point_pillar[pm.in_layer], minlength=len(pm.pillars))
    i = np.argmax(per_pillar)
    assert bands[:, pm.pillars[i, 0] - px, pm.pillars[i, 1] - py].sum() == per_pillar[i]
