"""The clutter paper's error matrix and the DynamicMap SA / DA / AA."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.metrics.removal import dynamic_scores, error_matrix


def _points(tp: int, fp: int, fn: int, tn: int) -> tuple[np.ndarray, np.ndarray]:
    reference = np.r_[np.ones(tp + fn, bool), np.zeros(fp + tn, bool)]
    removed = np.r_[np.ones(tp, bool), np.zeros(fn, bool), np.ones(fp, bool), np.zeros(tn, bool)]
    return reference, removed


def test_error_matrix_reproduces_the_papers_table_2() -> None:
    # Lee et al. 2020, Table 2 (drive 0056): 160,810 / 440,463 / 41,879 / 4,802,486
    reference, removed = _points(160_810, 440_463, 41_879, 4_802_486)
    e = error_matrix(reference, removed)
    assert e.total == 5_445_638
    # Table 3 formula: (160,810 + 4,802,486) / 5,445,638 = 91.1 (the paper prints 95)
    assert round(e.overall_accuracy) == 91
    assert round(e.clutter_omission) == 21
    assert round(e.clutter_commission) == 73
    assert round(e.map_omission) == 8
    assert round(e.map_commission) == 1
    d = e.as_dict()
    assert d["clutter_removed"] == 160_810 and d["map_kept"] == 4_802_486


def test_dynamic_scores() -> None:
    reference, removed = _points(tp=90, fp=2, fn=10, tn=98)
    s = dynamic_scores(reference, removed)
    assert s.sa == pytest.approx(98.0)
    assert s.da == pytest.approx(90.0)
    assert s.aa == pytest.approx(math.sqrt(98 * 90))


def test_unscored_points_and_empty_classes() -> None:
    reference, removed = _points(tp=0, fp=1, fn=0, tn=9)
    scored = np.ones(10, bool)
    scored[0] = False  # the false positive has no reference class
    s = dynamic_scores(reference, removed, static=scored)
    assert s.sa == 100.0
    assert math.isnan(s.da)  # no moving point: no DA, not a perfect one
    with pytest.raises(ValueError, match="reference has 10 points"):
        error_matrix(reference, removed[:5])
