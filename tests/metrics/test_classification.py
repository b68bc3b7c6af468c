"""Confusion matrix, per-class precision / recall / F, macro mean, binary scores."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.metrics.classification import (
    ClassScores,
    binary_scores,
    confusion_matrix,
    scores_from_confusion,
)


def test_confusion_matrix_hand_made() -> None:
    reference = np.array([0, 0, 0, 1, 1, 2, 2, 2, 2])
    predicted = np.array([0, 0, 1, 1, 2, 2, 2, 0, 2])
    expected = np.array(
        [
            [2, 1, 0],
            [0, 1, 1],
            [1, 0, 3],
        ]
    )
    cm = confusion_matrix(reference, predicted, 3)
    np.testing.assert_array_equal(cm, expected)
    assert cm.dtype == np.int64
    assert cm.sum() == len(reference)


def test_confusion_matrix_mask_and_absent_classes() -> None:
    reference = np.array([0, 1, 3, 3, 1])
    predicted = np.array([0, 3, 3, 1, 1])
    mask = np.array([True, True, True, False, False])
    cm = confusion_matrix(reference, predicted, 4, mask=mask)
    expected = np.zeros((4, 4), dtype=np.int64)
    expected[0, 0] = 1
    expected[1, 3] = 1
    expected[3, 3] = 1
    np.testing.assert_array_equal(cm, expected)


def test_confusion_matrix_rejects_out_of_range_and_mismatch() -> None:
    with pytest.raises(ValueError, match="reference labels"):
        confusion_matrix(np.array([0, 5]), np.array([0, 1]), 3)
    with pytest.raises(ValueError, match="predicted labels"):
        confusion_matrix(np.array([0, 1]), np.array([-1, 1]), 3)
    with pytest.raises(ValueError, match="one length"):
        confusion_matrix(np.array([0, 1]), np.array([0]), 3)
    # out-of-range labels are fine when masked away
    cm = confusion_matrix(np.array([0, 255]), np.array([1, 0]), 2, mask=np.array([True, False]))
    np.testing.assert_array_equal(cm, [[0, 1], [0, 0]])


def test_confusion_matrix_empty() -> None:
    cm = confusion_matrix(np.array([], dtype=int), np.array([], dtype=int), 2)
    np.testing.assert_array_equal(cm, np.zeros((2, 2)))


def test_scores_hand_computed() -> None:
    # rows = reference, columns = predicted
    cm = np.array(
        [
            [2, 1, 0],
            [0, 1, 1],
            [1, 0, 3],
        ]
    )
    s = scores_from_confusion(cm, ["a", "b", "c"])
    # a: tp 2, predicted 3, reference 3
    assert s.classes["a"].precision == pytest.approx(200 / 3)
    assert s.classes["a"].recall == pytest.approx(200 / 3)
    assert s.classes["a"].f1 == pytest.approx(200 / 3)
    assert s.classes["a"].support == 3
    # b: tp 1, predicted 2, reference 2
    assert s.classes["b"].precision == pytest.approx(50.0)
    assert s.classes["b"].recall == pytest.approx(50.0)
    # c: tp 3, predicted 4, reference 4
    assert s.classes["c"].precision == pytest.approx(75.0)
    assert s.classes["c"].recall == pytest.approx(75.0)
    assert s.accuracy == pytest.approx(600 / 9)
    assert s.macro.precision == pytest.approx((200 / 3 + 50 + 75) / 3)
    assert s.macro.support == 9
    assert s.macro_classes == ["a", "b", "c"]


def test_f_is_harmonic_mean_of_class_p_and_r() -> None:
    cm = np.array([[8, 2], [6, 4]])  # class 0: tp 8, predicted 14, reference 10
    s = scores_from_confusion(cm, ["x", "y"])
    p, r = 800 / 14, 80.0
    assert s.classes["x"].precision == pytest.approx(p)
    assert s.classes["x"].recall == pytest.approx(r)
    assert s.classes["x"].f1 == pytest.approx(2 * p * r / (p + r))
    p_y, r_y = 400 / 6, 40.0
    assert s.classes["y"].f1 == pytest.approx(2 * p_y * r_y / (p_y + r_y))
    assert s.macro.f1 == pytest.approx((2 * p * r / (p + r) + 2 * p_y * r_y / (p_y + r_y)) / 2)


def test_undefined_ratios_are_zero_and_macro_skips_absent_classes() -> None:
    # class "b" never occurs in the reference but is predicted once; "c" never predicted
    cm = np.array(
        [
            [3, 1, 0],
            [0, 0, 0],
            [2, 0, 0],
        ]
    )
    s = scores_from_confusion(cm, ["a", "b", "c"])
    b, c = s.classes["b"], s.classes["c"]
    assert (b.precision, b.recall, b.f1, b.support) == (0.0, 0.0, 0.0, 0)
    assert (c.precision, c.recall, c.f1, c.support) == (0.0, 0.0, 0.0, 2)
    values = [getattr(x, f) for x in s.classes.values() for f in ("precision", "recall", "f1")]
    assert np.isfinite(values).all()
    a = s.classes["a"]
    assert a.precision == pytest.approx(60.0)
    assert a.recall == pytest.approx(75.0)
    # macro over a and c only (b has no support)
    assert s.macro_classes == ["a", "c"]
    assert s.macro.precision == pytest.approx(30.0)
    assert s.macro.recall == pytest.approx(37.5)
    assert s.macro.f1 == pytest.approx(a.f1 / 2)
    assert s.macro.support == 6


def test_macro_exclude_reproduces_paper_table_one_overall() -> None:
    # Build a confusion whose per-class P / R match Table I closely, then check the reading:
    # Overall 91.5 / 91.4 / 91.5 is the mean over the three non-ground classes.
    names = ["short object", "high object", "phantom", "ground"]
    rows = {
        "short object": (86.5, 92.6, 89.5),
        "high object": (98.1, 93.2, 95.6),
        "phantom": (90.0, 88.5, 89.3),
        "ground": (99.7, 98.6, 99.2),
    }
    without_ground = np.mean([rows[n] for n in names[:3]], axis=0)
    with_ground = np.mean([rows[n] for n in names], axis=0)
    np.testing.assert_allclose(np.round(without_ground, 1), [91.5, 91.4, 91.5])
    assert not np.allclose(np.round(with_ground, 1), [91.5, 91.4, 91.5])

    cm = np.diag([100, 100, 100, 100]) + np.array(
        [[0, 0, 10, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]
    )
    s = scores_from_confusion(cm, names, macro_exclude=("ground",))
    assert s.macro_classes == names[:3]
    expected = np.mean([s.classes[n].precision for n in names[:3]])
    assert s.macro.precision == pytest.approx(expected)
    with pytest.raises(ValueError, match="unknown classes"):
        scores_from_confusion(cm, names, macro_exclude=("road",))


def test_as_dict_is_json_serialisable_and_round_trips() -> None:
    cm = confusion_matrix(np.array([0, 1, 1, 2]), np.array([0, 1, 2, 2]), 3)
    s = scores_from_confusion(cm, ["ground", "object", "phantom"])
    d = json.loads(json.dumps(s.as_dict()))
    assert d["names"] == ["ground", "object", "phantom"]
    assert d["confusion"] == [[1, 0, 0], [0, 1, 1], [0, 0, 1]]
    assert d["classes"]["object"]["recall"] == pytest.approx(50.0)
    assert d["classes"]["phantom"]["precision"] == pytest.approx(50.0)
    assert d["accuracy"] == pytest.approx(75.0)
    assert isinstance(d["classes"]["object"]["support"], int)
    assert set(d["macro"]) == {"precision", "recall", "f1", "support"}


def test_table_rows_and_markdown() -> None:
    cm = np.array([[3, 1], [0, 4]])
    s = scores_from_confusion(cm, ["ground", "phantom"])
    rows = s.table_rows()
    assert rows[0] == ["ground", "100.0", "75.0", "85.7", "4"]
    assert rows[1] == ["phantom", "80.0", "100.0", "88.9", "4"]
    assert rows[-1][0] == "overall"
    assert rows[-1][1:] == ["90.0", "87.5", "87.3", "8"]
    table = s.markdown().splitlines()
    assert table[0].startswith("| class |")
    assert table[-1] == "| overall | 90.0 | 87.5 | 87.3 | 8 |"


def test_binary_scores_table_two_style() -> None:
    reference = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0, 0], dtype=bool)
    predicted = np.array([1, 0, 0, 0, 1, 1, 0, 0, 0, 0], dtype=bool)
    s = binary_scores(reference, predicted)
    assert isinstance(s, ClassScores)
    p, r = 100 / 3, 25.0
    assert s.precision == pytest.approx(p)
    assert s.recall == pytest.approx(r)
    assert s.f1 == pytest.approx(2 * p * r / (p + r))
    assert s.support == 4
    # agrees with the two-class confusion matrix
    cm = confusion_matrix(reference.astype(int), predicted.astype(int), 2)
    assert scores_from_confusion(cm, ["other", "phantom"]).classes["phantom"] == s


def test_binary_scores_without_positives() -> None:
    s = binary_scores(np.zeros(5, bool), np.zeros(5, bool))
    assert (s.precision, s.recall, s.f1, s.support) == (0.0, 0.0, 0.0, 0)
