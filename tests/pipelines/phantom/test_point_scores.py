"""Point-level phantom scores follow SemanticKITTI's protocol: unlabelled and outlier points
are not scored, whatever the pipeline called them."""

from __future__ import annotations

import numpy as np

from app.pipelines.phantom.evaluation.classification_metrics import phantom_point_scores


def test_unlabelled_and_outlier_points_are_not_scored() -> None:
    # 4 moving car points (252), 4 static road points (40), 2 unlabelled (0), 2 outliers (1)
    semantic = np.array([252] * 4 + [40] * 4 + [0] * 2 + [1] * 2)
    moving = semantic >= 252
    in_layer = np.ones(len(semantic), dtype=bool)
    flags = np.array([1, 1, 1, 0] + [1, 0, 0, 0] + [1, 1] + [1, 0], dtype=bool)
    scores = phantom_point_scores(semantic, moving, in_layer, flags)
    assert scores.precision == 75.0  # 3 of the 4 scored calls; the 3 unscored calls do not count
    assert scores.recall == 75.0


def test_points_outside_the_layer_are_not_scored() -> None:
    semantic = np.array([252, 252, 40])
    moving = semantic >= 252
    in_layer = np.array([True, False, True])
    scores = phantom_point_scores(semantic, moving, in_layer, np.array([True, True, True]))
    assert scores.recall == 100.0 and scores.precision == 50.0
