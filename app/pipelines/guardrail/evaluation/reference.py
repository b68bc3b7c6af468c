"""What counts as a guardrail in a survey's reference labels, for the run's report and for
`mmsclean evaluate`: the simulator's guardrail index, or else SemanticKITTI's fence class, the
only class near it (not every urban fence is a guardrail). One rule, so a run's report.json and
`evaluate` on its labels score against the same truth. Also the reference per point of a run
(`point_reference`) and per slice (`slice_truth`), which label the training samples too."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from app.core.labels import FENCE
from app.io.survey import Survey
from app.pipelines.guardrail.scan_points import ScanPoints
from app.pipelines.guardrail.segmentation import SliceStage

# reference label kind -> what the scores are measured against
DESCRIPTIONS = {
    "guardrail": "simulator guardrails",
    "semantic": "SemanticKITTI fence (51); not every urban fence is a guardrail",
}


def reference_kind(kinds: Iterable[str]) -> str | None:
    """The reference to score guardrails against, the simulator's first; None when neither."""
    kinds = set(kinds)
    return next((kind for kind in DESCRIPTIONS if kind in kinds), None)


def guardrail_truth(kind: str, values: np.ndarray) -> np.ndarray:
    """True per point on a guardrail: a guardrail index >= 0, or the fence class (the low 16
    bits of a SemanticKITTI label)."""
    if kind == "guardrail":
        return np.asarray(values) >= 0
    return (np.asarray(values) & 0xFFFF) == FENCE


def slice_truth(stage: SliceStage, guardrail_index: np.ndarray) -> np.ndarray:
    """(K,) int64 reference slice label: 1 when most of its points belong to a guardrail.

    `guardrail_index` is the simulator's per-point guardrail index (-1 elsewhere), in the order
    of `stage.points`.
    """
    s = stage.slices
    on_rail = (guardrail_index[s.indices] >= 0).astype(np.int64)
    per_slice = np.add.reduceat(on_rail, s.offsets[:-1]) if len(s) else np.zeros(0, np.int64)
    return (2 * per_slice > np.diff(s.offsets)).astype(np.int64)


def point_reference(survey: Survey, points: ScanPoints, kind: str) -> np.ndarray:
    """A per-frame reference label (e.g. "guardrail", "semantic") in the order of `points`."""
    out = np.zeros(len(points), dtype=np.int64)
    for f in np.unique(points.frame):
        sel = points.frame == f
        out[sel] = survey.frames[int(f)].reference_labels()[kind][points.index[sel]]
    return out
