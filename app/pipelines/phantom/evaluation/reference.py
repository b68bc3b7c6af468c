"""Reference pillar classes of a map from per-point reference labels (evaluation, training).

Simulated surveys and SemanticKITTI both carry SemanticKITTI class ids; moving objects are either
flagged (simulator) or have the moving ids 252-259 (SemanticKITTI), which map back to their static
class. The pillar rule is the shared one (`app.core.labels`, also the simulator's): moving points
the majority of a pillar's non-ground points -> phantom; otherwise high vs short object by vote;
fewer than 3 non-ground points -> ground. Unlabelled (0) and outlier (1) points do not vote, and
point-level scores leave them out.
"""

from __future__ import annotations

import numpy as np

from app.core.labels import MOVING_TO_STATIC, Semantic, classify_pillar_groups
from app.pipelines.phantom.pillars import PillarMap


def static_and_moving(reference: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(static semantic id, moving flag) per point from a survey frame's reference labels."""
    semantic = reference["semantic"].astype(np.int64)
    if "moving" in reference:
        return semantic, reference["moving"].astype(bool)
    moving = semantic >= 252
    static = semantic.copy()
    for moving_id, static_id in MOVING_TO_STATIC.items():
        static[semantic == moving_id] = static_id
    return static, moving


NOT_SCORED = (Semantic.UNLABELED, 1)  # unlabelled, outlier: SemanticKITTI ignores them


def scored_points(semantic: np.ndarray) -> np.ndarray:
    """(N,) bool: points with a reference label. SemanticKITTI's evaluation ignores unlabelled
    and outlier points (and so does the clutter benchmark); on 05 the phantom calls on them lie
    10-16 m from any mover, which no reference says is static."""
    return ~np.isin(semantic, NOT_SCORED)


def reference_pillar_labels(pm: PillarMap, semantic: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """(P,) uint8 reference class of each occupied pillar of `pm`."""
    inside = pm.point_pillar >= 0
    voting = inside & scored_points(semantic)
    group = pm.point_pillar[inside]
    labels = classify_pillar_groups(group, semantic[inside], moving[inside], voting[inside])
    out = np.zeros(len(pm.pillars), dtype=np.uint8)
    out[: len(labels)] = labels
    return out
