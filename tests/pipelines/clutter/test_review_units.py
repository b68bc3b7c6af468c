"""Review units of one frame: which removed points each instance a reviewer judges owns."""

from __future__ import annotations

import numpy as np

from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.fusion import FrameEvidence
from app.pipelines.clutter.review_units import frame_instances


def test_review_units_of_one_frame() -> None:
    """A masked car cluster with a wheel point at ground level, a free-space cluster without a
    mask, and two loose free-space points on the ground far from everything."""
    xyz = np.array(
        [
            [10, 0, 1.0], [10.2, 0, 1.0], [10.4, 0, 1.0],  # car cluster 0: seeds 0, 1
            [10.1, 0, 0.9],  # wheel: masked, ground level (unclustered), 0.14 m from the car
            [20, 5, 1.0], [20.2, 5, 1.0],  # free-space cluster 1 (a passing cyclist, unseen)
            [30, -5, 0.0], [30.1, -5, 0.0],  # free-space points on the ground
            [40, 0, 0.0],  # road, kept
        ]
    )  # fmt: skip
    removed = np.array([1, 1, 1, 1, 1, 1, 1, 1, 0], bool)
    evidence = FrameEvidence(
        in_view=np.array([1, 1, 1, 1, 0, 0, 0, 0, 0], bool),
        camera_removed=np.array([1, 1, 1, 1, 0, 0, 0, 0, 0], bool),
        padded=np.array([1, 1, 1, 1, 0, 0, 0, 0, 0], bool),
        cluster=np.array([0, 0, 0, -1, 1, 1, -1, -1, -1], np.int32),
        free=np.array([0, 0, 0, 0, 1, 1, 1, 1, 0], bool),
        instance=np.array([0, 0, -1, -1, -1, -1, -1, -1, -1], np.int32),
        mask_class=np.array([3, 3, 3, 3, 0, 0, 0, 0, 0], np.uint8),
    )
    cluster_track = np.array([4, -1], np.int32)  # the car is track 4, the cyclist untracked
    units = frame_instances(
        xyz,
        removed,
        evidence,
        cluster_track,
        track_moving=np.array([0, 0, 0, 0, 0], bool),
        track_class=np.array([0, 0, 0, 0, 3], np.uint8),
        config=ClutterConfig(),
    )
    assert units.owner.tolist() == [0, 0, 0, 0, 1, 1, 2, 2, -1]
    assert units.class_names == ["car", "free-space", "free-space"]
    assert units.track_id.tolist() == [4, -1, -1]
    assert units.moving == [False, True, True]
