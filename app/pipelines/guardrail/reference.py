"""What counts as a guardrail in a survey's reference labels, for the run's report and for
`mmsclean evaluate`: the simulator's guardrail index, or else SemanticKITTI's fence class, the
only class near it (not every urban fence is a guardrail). One rule, so a run's report.json and
`evaluate` on its labels score against the same truth."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from app.core.labels import FENCE

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
