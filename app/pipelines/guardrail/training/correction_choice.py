"""The adjacency correction chosen with a classifier, on its validation surveys.

The paper's correction (fill short gaps, drop lone slices) at a 0.5 threshold suits a classifier
whose slice errors are scattered. A classifier for another scanner errs otherwise: on rotating
scanners a guardrail is a few rings at grazing angles, and the geometry head's false calls come
in short runs on fences and kerbs, which a higher threshold removes better than the lone-slice
rule, and its true slices are often alone in their chain, which only `keep_confident` saves
(correction.py). So the threshold, `max_gap`, `max_isolated` and `keep_confident` are chosen
per classifier on the slices of its validation surveys (never its held-out ones) and kept in
its card (`correction`); a run uses them unless its config sets them
(`GuardrailConfig.with_correction`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.io import open_survey
from app.metrics.classification import binary_scores
from app.pipelines.guardrail.config import PAPER_CORRECTION, GuardrailConfig
from app.pipelines.guardrail.correction import correct_labels
from app.pipelines.guardrail.evaluation.reference import slice_truth
from app.pipelines.guardrail.pipeline import GuardrailPipeline, confident
from app.pipelines.guardrail.run import reference_points
from app.pipelines.guardrail.slices import SliceSet
from app.pipelines.guardrail.training.dataset import simulated_survey

THRESHOLDS = tuple(round(0.3 + 0.05 * k, 2) for k in range(11))  # 0.3 .. 0.8
# both of the paper's steps stay on (at least one slice filled, a lone slice dropped): with
# either off the slice F on validation rose a little, but stray end slices kept by
# max_isolated 0 pulled far points into the beam units (held-out beam section 0.7 -> 5.1 cm)
MAX_GAPS = tuple(range(1, 7))
MAX_ISOLATED = tuple(range(1, 5))
KEEP_CONFIDENT = (None, 0.8, 0.85, 0.9, 0.95)  # None: the paper's, every lone slice goes


@dataclass
class ValidationSlices:
    """One validation survey's slices, the classifier's probability and the reference."""

    slices: SliceSet
    probability: np.ndarray  # (K,)
    truth: np.ndarray  # (K,) bool: a guardrail slice by the simulator's reference


def validation_slices(
    model: Path, seeds: list[int], length: float, sensor: str
) -> list[ValidationSlices]:
    """Classify the slices of each validation survey with the model's default head."""
    pipeline = GuardrailPipeline(GuardrailConfig(reconstruct=False), model)
    out = []
    for seed in seeds:
        survey = open_survey(simulated_survey(seed, length, sensor=sensor), "sim")
        result = pipeline.run(survey)
        found = reference_points(survey, result)
        if found is None:
            raise ValueError(f"validation survey {seed} has no guardrail reference")
        truth = slice_truth(result.stage, np.where(found[0], 0, -1)).astype(bool)
        out.append(ValidationSlices(result.stage.slices, result.probability, truth))
    return out


def corrected_f1(
    parts: list[ValidationSlices], threshold: float, gap: int, isolated: int, keep: float | None
):
    truth = np.concatenate([p.truth for p in parts])
    labels = np.concatenate(
        [
            correct_labels(
                p.slices,
                p.probability >= threshold,
                max_gap=gap,
                max_isolated=isolated,
                keep=confident(p.probability, keep),
            )
            for p in parts
        ]  # fmt: skip
    ).astype(bool)
    return binary_scores(truth, labels)


def choose_correction(parts: list[ValidationSlices], seeds: list[int]) -> dict:
    """The settings with the best slice F over all validation slices (ties: the first in grid
    order, lowest threshold, gap and isolated run first, then the paper's lone-slice rule), with
    the paper's for comparison."""
    best, best_f = dict(PAPER_CORRECTION), -1.0
    grid = itertools.product(THRESHOLDS, MAX_GAPS, MAX_ISOLATED, KEEP_CONFIDENT)
    for threshold, gap, isolated, keep in grid:
        f = corrected_f1(parts, threshold, gap, isolated, keep).f1
        if f > best_f + 1e-9:
            best = {"threshold": threshold, "max_gap": gap, "max_isolated": isolated,
                    "keep_confident": keep}  # fmt: skip
            best_f = f
    paper = corrected_f1(parts, *PAPER_CORRECTION.values())  # type: ignore[arg-type]
    slices = int(sum(len(p.truth) for p in parts))
    return {
        **best,
        "chosen_on": {"simulation_seeds": list(seeds), "slices": slices},
        "validation_slice_f": round(best_f, 2),
        "paper_validation_slice_f": round(paper.f1, 2),
    }
