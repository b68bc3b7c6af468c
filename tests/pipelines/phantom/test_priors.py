"""Class priors: Bayes' rule from balanced training classes to the map's class frequencies."""

from __future__ import annotations

import numpy as np
import pytest

from app.pipelines.phantom.priors import apply_priors, class_priors


def test_priors_are_frequencies_with_a_floor() -> None:
    priors = class_priors([0, 300, 600, 100])
    assert priors.sum() == pytest.approx(1.0)
    assert priors[0] > 0  # a class the training maps lacked is not ruled out
    assert priors[2] == pytest.approx(2 * priors[1], rel=1e-3)
    with pytest.raises(ValueError, match="no judged pillars"):
        class_priors([0, 0, 0, 0])


def test_bayes_moves_a_doubtful_pillar_to_the_common_class() -> None:
    probs = np.array([[0.0, 0.1, 0.44, 0.46], [0.0, 0.0, 0.05, 0.95]], dtype=np.float32)
    priors = np.array([0.03, 0.33, 0.56, 0.08])
    adjusted = apply_priors(probs, priors, 1.0)
    assert np.allclose(adjusted.sum(axis=1), 1.0)
    assert adjusted[0].argmax() == 2  # 46 % phantom vs 44 % short: short is 7x more common
    assert adjusted[1].argmax() == 3  # a confident phantom stays a phantom
    # the posterior ratio is the likelihood ratio times the prior ratio (Bayes)
    assert adjusted[0, 2] / adjusted[0, 3] == pytest.approx(0.44 / 0.46 * 0.56 / 0.08, rel=1e-5)
    assert apply_priors(probs, priors, 0.0) is probs
