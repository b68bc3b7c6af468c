"""The one rule for what counts as a guardrail in reference labels (run reports and
`mmsclean evaluate` both use it)."""

from __future__ import annotations

import numpy as np

from app.core.labels import FENCE
from app.pipelines.guardrail.evaluation.reference import (
    DESCRIPTIONS,
    guardrail_truth,
    reference_kind,
)


def test_the_simulator_reference_comes_first_then_semantickitti() -> None:
    assert reference_kind(["semantic", "guardrail", "instance"]) == "guardrail"
    assert reference_kind(["semantic", "instance"]) == "semantic"
    assert reference_kind(["instance"]) is None
    assert "fence (51)" in DESCRIPTIONS["semantic"]


def test_guardrail_index_and_fence_class_with_instance_bits() -> None:
    assert guardrail_truth("guardrail", np.array([-1, 0, 3])).tolist() == [False, True, True]
    semantic = np.array([FENCE, (7 << 16) | FENCE, 40, (FENCE << 16) | 40], dtype=np.uint32)
    assert guardrail_truth("semantic", semantic).tolist() == [True, True, False, False]
