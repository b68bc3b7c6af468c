"""The clutter run against reference labels: the paper's error matrix and SA / DA / AA, inside
the camera view and on the full 360 degree map.

References (SemanticKITTI ids; the simulator writes the same ids and a per-point `moving` flag):
- `dynamic`: the moving classes 252-259, or the simulator's `moving` flag;
- `clutter`: every movable class, parked or moving (cars, bicycles, buses, motorcycles, trams,
  trucks, other vehicles, persons, bicyclists, motorcyclists: 10-32 and 252-259).
Unlabelled (0) and outlier (1) points have no reference class and are left out of every score.
"""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np

from app.core.labels import MOVABLE_IDS, MOVING_IDS, UNSCORED_IDS
from app.io.survey import Survey
from app.metrics.removal import DynamicScores, ErrorMatrix, error_matrix


def reference_masks(
    semantic: np.ndarray, moving: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Per point: `scored`, `dynamic` (moving) and `clutter` (movable) reference flags."""
    semantic = np.asarray(semantic) & 0xFFFF
    dynamic = np.isin(semantic, MOVING_IDS)
    if moving is not None:
        dynamic |= np.asarray(moving).astype(bool)
    return {
        "scored": ~np.isin(semantic, UNSCORED_IDS),
        "dynamic": dynamic,
        "clutter": np.isin(semantic, MOVABLE_IDS) | dynamic,
    }


def removal_metrics(
    semantic: np.ndarray,
    removed: np.ndarray,
    in_view: np.ndarray,
    moving: np.ndarray | None = None,
) -> dict[str, dict[str, dict]]:
    """{scope: {reference: {"error_matrix": ..., "scores": SA/DA/AA}}} for scope in view / 360."""
    return metrics_from_counts(removal_counts(semantic, removed, in_view, moving))


def removal_counts(
    semantic: np.ndarray,
    removed: np.ndarray,
    in_view: np.ndarray,
    moving: np.ndarray | None = None,
) -> dict[str, dict[str, dict[str, int]]]:
    """The error matrices behind `removal_metrics`: counts, so that the parts of a survey
    (a tiled run's tiles) add up (`add_removal_counts`) to the whole survey's."""
    ref = reference_masks(semantic, moving)
    removed = np.asarray(removed, dtype=bool)
    out: dict[str, dict[str, dict[str, int]]] = {}
    for scope, where in (("in_view", ref["scored"] & in_view), ("full", ref["scored"])):
        out[scope] = {
            kind: asdict(error_matrix(ref[kind][where], removed[where]))
            for kind in ("dynamic", "clutter")
        }
    return out


def add_removal_counts(total: dict | None, part: dict) -> dict:
    """`removal_counts` of two parts of a survey added (`total` None: the first part)."""
    if total is None:
        return json.loads(json.dumps(part))
    return {
        scope: {
            kind: {k: total[scope][kind][k] + n for k, n in counts.items()}
            for kind, counts in kinds.items()
        }
        for scope, kinds in part.items()
    }


def metrics_from_counts(counts: dict) -> dict[str, dict[str, dict]]:
    """`removal_metrics` from its error matrices: SA / DA / AA are ratios of the same counts
    (static kept = map kept, dynamic removed = clutter removed)."""
    out: dict[str, dict[str, dict]] = {}
    for scope, kinds in counts.items():
        out[scope] = {}
        for kind, values in kinds.items():
            matrix = ErrorMatrix(**values)
            scores = DynamicScores(
                static_points=matrix.map_removed + matrix.map_kept,
                static_kept=matrix.map_kept,
                dynamic_points=matrix.clutter_removed + matrix.clutter_kept,
                dynamic_removed=matrix.clutter_removed,
            )
            out[scope][kind] = {"error_matrix": matrix.as_dict(), "scores": scores.as_dict()}
    return out


def survey_removal_counts(
    survey: Survey, frames: np.ndarray, removed: list[np.ndarray], in_view: list[np.ndarray]
) -> dict | None:
    """`removal_counts` of the survey's frames `frames` (indices) against their reference
    labels, added frame by frame (nothing holds the survey's labels); None without them."""
    if "semantic" not in survey.reference_label_kinds:
        return None
    total = None
    for k, gone, seen in zip(np.asarray(frames).tolist(), removed, in_view, strict=True):
        reference = survey.frames[k].reference_labels()
        moving = reference["moving"] if "moving" in survey.reference_label_kinds else None
        total = add_removal_counts(total, removal_counts(reference["semantic"], gone, seen, moving))
    return total
