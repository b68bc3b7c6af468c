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
    binary_counts,
    binary_from_counts,
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


def phantom_point_counts(
    semantic: np.ndarray, moving: np.ndarray, in_layer: np.ndarray, flags: np.ndarray
) -> list[int]:
    """Point-level phantom detection: a removed point should belong to a moving object. Counted
    over the pillar layer's points with a reference label (`scored_points`)."""
    scored = in_layer & scored_points(semantic)
    return binary_counts(moving & scored, flags & scored)


def phantom_point_scores(
    semantic: np.ndarray, moving: np.ndarray, in_layer: np.ndarray, flags: np.ndarray
) -> ClassScores:
    return binary_from_counts(*phantom_point_counts(semantic, moving, in_layer, flags))


def metric_counts(
    result: PhantomResult,
    points: np.ndarray | None = None,
    pillars: np.ndarray | None = None,
    baselines: dict[str, np.ndarray] | None = None,
) -> dict:
    """The additive part of the metrics (confusion matrices, detection counts) over the points
    and pillars selected, (N,) and (P,) bool, all by default: a tile counts the ones it owns
    and a survey's metrics are `metrics_from_counts` of the tiles' sums (`add_counts`).
    `baselines` maps a method name to per-point phantom flags."""
    semantic, moving = static_and_moving(result.map.reference)
    pm = result.pillar_map
    points = np.ones(len(pm.point_pillar), dtype=bool) if points is None else points
    pillars = np.ones(len(pm.pillars), dtype=bool) if pillars is None else pillars
    ref_pillars = reference_pillar_labels(pm, semantic, moving)
    in_layer = (pm.point_pillar >= 0) & points
    counts: dict = {"pillars": int(pillars.sum())}
    for key, predicted in (("pillar_raw", result.raw_labels), ("pillar", result.pillar_labels)):
        counts[key] = confusion_matrix(ref_pillars, predicted, 4, mask=pillars).tolist()
    ref_points = point_labels(pm, ref_pillars)
    counts["point"] = confusion_matrix(ref_points, result.point_labels, 4, mask=in_layer).tolist()
    phantom = {"mmsclean": result.point_labels == PillarClass.phantom, **(baselines or {})}
    counts["phantom_points"] = {
        name: phantom_point_counts(semantic, moving, in_layer, flags)
        for name, flags in phantom.items()
    }
    return counts


def add_counts(total: dict | None, part: dict) -> dict:
    """The sum of two `metric_counts` (None: nothing yet)."""
    if total is None:
        return part
    out = {"pillars": total["pillars"] + part["pillars"]}
    for key in ("pillar_raw", "pillar", "point"):
        out[key] = (np.asarray(total[key]) + np.asarray(part[key])).tolist()
    out["phantom_points"] = {
        name: [a + b for a, b in zip(total["phantom_points"][name], counts, strict=True)]
        for name, counts in part["phantom_points"].items()
    }
    return out


def metrics_from_counts(counts: dict) -> dict:
    """Metrics as a JSON-ready dict from `metric_counts` (one map's, or tiles' summed)."""
    names = list(CLASS_NAMES)
    out: dict = {"pillars": counts["pillars"]}
    for key in ("pillar_raw", "pillar", "point"):
        out[key] = scores_from_confusion(
            np.asarray(counts[key], dtype=np.int64), names, macro_exclude=PAPER_OVERALL_EXCLUDES
        ).as_dict()
    out["phantom_points"] = {
        name: binary_from_counts(*c).as_dict() for name, c in counts["phantom_points"].items()
    }
    return out


def evaluate(result: PhantomResult, baselines: dict[str, np.ndarray] | None = None) -> dict:
    """Metrics of a whole map as a JSON-ready dict (`metric_counts`, `metrics_from_counts`)."""
    return metrics_from_counts(metric_counts(result, baselines=baselines))
