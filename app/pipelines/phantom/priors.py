"""Class priors: from the balanced training set to the class frequencies of a real map.

The CNN is trained on the same number of pillars per class (the paper's 10,000 each), so its
softmax estimates p(class | window) under equal priors. On a street map the pillars the CNN judges
are far from balanced (phantoms are a few per cent of them), and equal priors make it call every
doubtful parked car a phantom. Bayes' rule moves the posterior to the map's priors:

    p_map(c | x)  ~  p_train(c | x) * (pi_map(c) / pi_train(c)) ** w

pi_map is estimated from the training maps (class frequencies among their judged pillars, stored
in the model card as `class_priors`), pi_train is uniform, and the weight w (`prior_weight`,
1 = plain Bayes, 0 = the paper's argmax) was chosen on simulated validation maps, not on the maps
reported as the evaluation (bench/RESULTS.md).
"""

from __future__ import annotations

import numpy as np


def class_priors(judged_counts: np.ndarray) -> np.ndarray:
    """(4,) class frequencies from judged-pillar counts per class (each class at least 0.1 %, so
    that a class the training maps lacked is not ruled out)."""
    counts = np.asarray(judged_counts, dtype=np.float64)
    if counts.sum() <= 0:
        raise ValueError("no judged pillars to estimate class priors from")
    priors = np.maximum(counts / counts.sum(), 1e-3)
    return priors / priors.sum()


def apply_priors(probabilities: np.ndarray, priors: np.ndarray, weight: float) -> np.ndarray:
    """(P, 4) posteriors under the map priors (rows sum to 1); weight 0 returns them unchanged."""
    if weight == 0 or priors is None:
        return probabilities
    ratio = (np.asarray(priors, dtype=np.float64) * len(priors)) ** weight
    adjusted = probabilities * ratio.astype(probabilities.dtype)
    return adjusted / adjusted.sum(axis=1, keepdims=True)
