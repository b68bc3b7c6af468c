"""Time as evidence: distinct scanner passes per voxel as the CNN's second input channel."""

from __future__ import annotations

import numpy as np
import torch

from app.geometry.ground import estimate_ground
from app.io.accumulate import accumulate
from app.io.survey import MAP_FRAME_ID, Frame, PointCloud, Survey
from app.pipelines.phantom.classify import classify_dense, classify_windows, window_tensor
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.network import PillarCNN
from app.pipelines.phantom.pillars import build_pillar_map
from app.pipelines.phantom.training.dataset import LabelledMap, frame_windows, pillar_samples
from tests.pipelines.phantom.test_core import street

CFG = PhantomConfig()


def test_a_voxel_counts_each_pass_once() -> None:
    # one voxel hit 5 times in pass 0 and once in passes 3 and 7; another only in pass 2
    xyz = np.array([[0.05, 0.05, 1.05]] * 7 + [[1.05, 1.05, 1.05]] + [[5.0, 5.0, 0.0]])
    passes = np.array([0, 0, 0, 0, 0, 3, 7, 2, 1])
    pm = build_pillar_map(xyz, estimate_ground(xyz), CFG, passes)
    block = pm.channel_block(0, 0, 12, 12, passes=True)
    assert block.shape == (2, 30, 12, 12)
    ground = estimate_ground(xyz).height(xyz[:1])[0]
    vz = int(np.floor((1.05 - ground) / 0.1))
    assert block[0, vz, 0, 0] == 7 and block[1, vz, 0, 0] == 3
    assert block[0, vz, 10, 10] == 1 and block[1, vz, 10, 10] == 1
    assert (block[1] <= block[0]).all()


def random_passes_net() -> PillarCNN:
    torch.manual_seed(1)
    net = PillarCNN(context=4, passes=True)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 0.3)
    return net.eval()


def test_dense_equals_per_window_with_passes() -> None:
    xyz = street(30_000)
    passes = np.random.default_rng(0).integers(0, 10, len(xyz))
    pm = build_pillar_map(xyz, estimate_ground(xyz), CFG, passes)
    which = pm.candidates()[:300]
    net = random_passes_net()
    windows = classify_windows(net, pm, which=which)
    dense = classify_dense(net, pm, tile=16, which=which)
    assert np.abs(windows - dense).max() < 1e-4
    x = window_tensor(pm, pm.pillars[which[:3]], passes=True)
    assert x.shape == (3, 2, 30, 24, 24)


def test_frames_are_passes_and_map_times_are_binned() -> None:
    frames = [
        Frame(i, f"{i:06d}", np.eye(4), _load_points=lambda: PointCloud(np.zeros((4, 3))))
        for i in range(3)
    ]
    drive = Survey("d", source=None, format="sim", frames=frames)  # type: ignore[arg-type]
    assert accumulate(drive, with_passes=True).passes.tolist() == [0] * 4 + [1] * 4 + [2] * 4
    times = np.array([100.00, 100.05, 100.12, 100.31])
    cloud = PointCloud(np.zeros((4, 3)), time=times)
    one = Frame(0, MAP_FRAME_ID, np.eye(4), _load_points=lambda: cloud)
    lmap = Survey("m", source=None, format="las", frames=[one])  # type: ignore[arg-type]
    assert accumulate(lmap, with_passes=True).passes.tolist() == [0, 0, 1, 3]
    untimed = Frame(0, MAP_FRAME_ID, np.eye(4), _load_points=lambda: PointCloud(np.zeros((4, 3))))
    plain = Survey("p", source=None, format="las", frames=[untimed])  # type: ignore[arg-type]
    assert accumulate(plain, with_passes=True).passes is None


def test_training_windows_carry_passes_and_frame_windows_cut_drives() -> None:
    xyz = street(40_000)
    n = len(xyz)
    semantic = np.full(n, 40)
    semantic[xyz[:, 2] - (100 + 0.05 * xyz[:, 0]) > 0.2] = 50
    moving = np.zeros(n, dtype=bool)
    lmap = LabelledMap(xyz, semantic, moving, "street", passes=np.arange(n) % 25)
    windows = frame_windows(lmap, 10)
    assert [len(w) for w in windows] == [int(((lmap.passes // 10) == k).sum()) for k in range(3)]
    assert windows[1].passes.min() == 10 and windows[1].passes.max() == 19
    samples = pillar_samples(lmap, CFG, np.random.default_rng(0), max_per_class=50, passes=True)
    assert samples.x.shape[1:] == (2, 30, 24, 24)
    assert (samples.x[:, 1] <= samples.x[:, 0]).all()
