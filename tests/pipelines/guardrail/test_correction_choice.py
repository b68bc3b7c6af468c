"""The adjacency correction chosen with a classifier on its validation surveys, and runs using
it unless their config says otherwise."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.pipelines.guardrail.classifier import SliceHead, save_heads
from app.pipelines.guardrail.config import PAPER_CORRECTION, GuardrailConfig
from app.pipelines.guardrail.pipeline import GuardrailPipeline
from app.pipelines.guardrail.training.correction_choice import (
    ValidationSlices,
    choose_correction,
)
from tests.pipelines.guardrail.test_segmentation import _chains


def validation_parts() -> list[ValidationSlices]:
    """A 12-slice guardrail whose classifier dips below 0.5 at two slices, beside a 4-slice
    fence it scores 0.6 to 0.65: the paper's 0.5 keeps the fence and cuts the guardrail."""
    slices = _chains()
    order = np.lexsort((slices.station_index, slices.component))
    sorted_probability = np.array([0.9, 0.9, 0.4, 0.9, 0.9, 0.9, 0.45, 0.9, 0.9, 0.9, 0.9, 0.9,
                                   0.6, 0.65, 0.65, 0.6])  # fmt: skip
    probability, truth = np.empty(16), np.empty(16, dtype=bool)
    probability[order] = sorted_probability
    truth[order] = np.arange(16) < 12
    return [ValidationSlices(slices, probability, truth)]


def test_the_choice_beats_the_paper_settings_on_validation() -> None:
    chosen = choose_correction(validation_parts(), [781])
    assert chosen["validation_slice_f"] == 100.0
    assert chosen["paper_validation_slice_f"] < 100.0
    # ties go to the first in grid order: the lowest threshold, then gap, then isolated run
    # (here 0.3 keeps the dips and dropping runs of four takes the fence); the paper's two
    # steps stay on (gap and isolated run at least 1)
    assert (chosen["threshold"], chosen["max_gap"], chosen["max_isolated"]) == (0.3, 1, 4)
    assert chosen["keep_confident"] is None  # the fence's 0.65 must not be kept
    assert chosen["chosen_on"] == {"simulation_seeds": [781], "slices": 16}


def test_a_run_uses_the_card_correction_unless_its_config_sets_one(tmp_path: Path) -> None:
    heads = {name: SliceHead(name, 3) for name in ("image+geometry", "image", "geometry")}
    correction = {"threshold": 0.75, "max_gap": 1, "max_isolated": 0, "keep_confident": 0.9}
    path = save_heads(tmp_path / "m.pt", heads, {"correction": correction})
    config = GuardrailPipeline(GuardrailConfig(), path).config
    assert (config.threshold, config.max_gap, config.max_isolated) == (0.75, 1, 0)
    assert config.keep_confident == 0.9
    told = GuardrailPipeline(GuardrailConfig(threshold=0.4, max_isolated=2), path).config
    assert (told.threshold, told.max_gap, told.max_isolated) == (0.4, 1, 2)
    older = GuardrailPipeline(GuardrailConfig(), save_heads(tmp_path / "o.pt", heads, {})).config
    assert older.model_dump(include=set(PAPER_CORRECTION)) == PAPER_CORRECTION


def test_a_confident_lone_slice_is_kept_when_the_validation_says_so() -> None:
    """Rotating scanners: a true guardrail slice alone in its chain (its rail broken into
    components) with a sure classifier; the lone fence slice is unsure."""
    slices = _chains()
    order = np.lexsort((slices.station_index, slices.component))
    sorted_probability = np.full(16, 0.1)
    sorted_probability[[0, 1, 2, 5]] = 0.95  # a run and a lone sure slice on the guardrail
    sorted_probability[13] = 0.7  # a lone unsure slice on the fence
    probability, truth = np.empty(16), np.empty(16, dtype=bool)
    probability[order] = sorted_probability
    truth[order] = np.isin(np.arange(16), [0, 1, 2, 5])
    chosen = choose_correction([ValidationSlices(slices, probability, truth)], [781])
    assert chosen["validation_slice_f"] == 100.0
    assert chosen["keep_confident"] is not None and chosen["keep_confident"] <= 0.95
