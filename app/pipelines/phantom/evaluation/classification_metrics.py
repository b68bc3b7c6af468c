"""The paper's metrics (Table I: precision / recall / F per class and overall, confusion matrix;
Table II: phantom detection against the two baselines) for a run on a survey with reference
labels. Pillar level is what the paper reports; point level is what a cleaned map is made of.

"Overall" (`macro`) is the mean over the three object classes, ground left out: that is how
Table I's overall row is computed (91.5 = mean of 89.5, 95.6, 89.3); `accuracy` is the micro
rate over all four."""

from __future__ import annotations

import numpy as np

from app.core.labels import PillarClass
from app.metrics.classification import (
    ClassScores,
    binary_scores,
    confusion_matrix,
    scores_from_confusion,
)
from app.pipelines.phantom.evaluation.reference import (
    reference_pillar_labels,
    scored_points,
    static_and_moving,
)
from app.pipelines.phantom.network import CLASS_NAMES
from app.pipelines.phantom.pipeline import PhantomResult
from app.pipelines.phantom.point_labels import point_labels

PAPER_OVERALL_EXCLUDES = ("ground",)


def phantom_point_scores(
    semantic: np.ndarray, moving: np.ndarray, in_layer: np.ndarray, flags: np.ndarray
) -> ClassScores:
    """Point-level phantom detection: a removed point should belong to a moving object. Scored
    over the pillar layer's points with a reference label (`scored_points`)."""
    scored = in_layer & scored_points(semantic)
    return binary_scores(moving & scored, flags & scored)


def evaluate(result: PhantomResult, baselines: dict[str, np.ndarray] | None = None) -> dict:
    """Metrics as a JSON-ready dict; `baselines` maps a method name to per-point phantom flags."""
    reference = result.map.reference
    semantic, moving = static_and_moving(reference)
    pm = result.pillar_map
    ref_pillars = reference_pillar_labels(pm, semantic, moving)
    names = list(CLASS_NAMES)
    out: dict = {"pillars": int(len(pm.pillars))}
    for key, predicted in (("pillar_raw", result.raw_labels), ("pillar", result.pillar_labels)):
        confusion = confusion_matrix(ref_pillars, predicted, 4)
        out[key] = scores_from_confusion(
            confusion, names, macro_exclude=PAPER_OVERALL_EXCLUDES
        ).as_dict()
    in_layer = pm.point_pillar >= 0
    ref_points = point_labels(pm, ref_pillars)
    confusion = confusion_matrix(ref_points, result.point_labels, 4, mask=in_layer)
    out["point"] = scores_from_confusion(
        confusion, names, macro_exclude=PAPER_OVERALL_EXCLUDES
    ).as_dict()
    phantom = {"mmsclean": result.point_labels == PillarClass.phantom}
    phantom.update(baselines or {})
    out["phantom_points"] = {
        name: phantom_point_scores(semantic, moving, in_layer, flags).as_dict()
        for name, flags in phantom.items()
    }
    return out
