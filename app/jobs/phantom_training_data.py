"""What `train:phantom` learns from, and whether it can: the one check the retraining trigger
runs before it queues the job and the task runs again before and after it looks the labels up in
the survey maps, so the trigger queues only what can train and a job that cannot fails with one
line saying why (not a numpy error from an empty sample set).

Training needs, with the task's config: at least `min_labels` human labels; map blocks held out
for validation with labels left outside them (a survey whose labels lie in one block gives
validation labels only); labelled pillars with points on both sides (a pillar with no points in
its survey's map gives no sample); and at least `min_classes` classes among the training labels
(a network fine-tuned on one class learns to answer it everywhere, and validated on that class
alone it would even look better than the one it replaces), two of them with `min_class_labels`
pillars each (fine-tuning leaves rarer classes out).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from app.core.labels import PillarClass
from app.metrics.splits import held_out_blocks
from app.store.pillar_labels import STORE_GRID
from app.store.training_labels import SurveyLabels

if TYPE_CHECKING:
    from app.jobs.training_tasks import PhantomRetrainConfig


def held_out(labels: SurveyLabels, cfg: PhantomRetrainConfig) -> np.ndarray:
    """(L,) True for the survey's labels in the map blocks held out for validation (every
    labelled class on both sides where its labels span two blocks or more)."""
    ix, iy = STORE_GRID.decode(labels.cells)
    centres = STORE_GRID.cell_center(ix, iy)
    return held_out_blocks(centres, cfg.block_size, cfg.holdout, cfg.seed, labels.classes)


@dataclass(frozen=True)
class ClassCounts:
    """Per class (ground, high, short, phantom) what training and validation would get."""

    labels: int  # human labels found
    train: np.ndarray  # (4,) outside the held-out blocks
    held_out: np.ndarray  # (4,) inside them
    with_points: bool  # counted only pillars known to hold points (else every label)
    unmapped: int = 0  # with_points: labels left out, on surveys no phantom run has mapped


def label_counts(
    labels: dict[int, SurveyLabels], cfg: PhantomRetrainConfig, with_points: bool = False
) -> ClassCounts:
    """The counts from the labels alone; WITH_POINTS: count only the labels whose pillar a
    survey's last phantom run found points in (`mapped`). A survey no phantom run has mapped
    counts for nothing then: which of its pillars hold points is unknown without reading its
    whole map, and a trigger that guessed would queue jobs bound to fail."""
    train, held = np.zeros(4, np.int64), np.zeros(4, np.int64)
    unmapped = 0
    for survey in labels.values():
        inside = held_out(survey, cfg)
        usable: np.ndarray | bool = True
        if with_points:
            usable = survey.mapped if survey.mapped is not None else False
            unmapped += 0 if survey.mapped is not None else len(survey.cells)
        train += np.bincount(survey.classes[~inside & usable], minlength=4)[:4]
        held += np.bincount(survey.classes[inside & usable], minlength=4)[:4]
    total = sum(len(s.cells) for s in labels.values())
    return ClassCounts(total, train, held, with_points, unmapped)


def training_blocker(counts: ClassCounts, cfg: PhantomRetrainConfig) -> str | None:
    """Why `train:phantom` cannot train on these counts (one line), or None when it can."""
    if counts.labels < cfg.min_labels:
        return f"{counts.labels} human pillar labels; retraining needs at least {cfg.min_labels}"
    for side, part in (("outside", counts.train), ("inside", counts.held_out)):
        if part.sum():
            continue
        if counts.with_points and counts.unmapped:
            return (
                f"no labelled pillar {side} the map blocks held out for validation is known to "
                f"hold points: {counts.unmapped:,} labels lie on surveys no phantom run has "
                "mapped (run phantom on them, or retrain by hand)"
            )
        if counts.with_points:
            return (
                f"no labelled pillar {side} the map blocks held out for validation has points "
                "in its survey's map (labels outside the surveyed area?)"
            )
        return (
            f"the labels cover too few map blocks of {cfg.block_size:g} m to hold some out for "
            "validation (label pillars in more places)"
        )
    present = [PillarClass(int(c)).name for c in np.flatnonzero(counts.train)]
    if len(present) < cfg.min_classes:
        return (
            f"the training labels hold {len(present)} class(es) ({', '.join(present)}); "
            f"retraining needs at least {cfg.min_classes}"
        )
    enough = np.flatnonzero(counts.train >= cfg.min_class_labels)
    if len(enough) < max(cfg.min_classes, 2):
        held = ", ".join(f"{PillarClass(c).name} {n}" for c, n in enumerate(counts.train) if n)
        return (
            f"retraining needs {max(cfg.min_classes, 2)} classes with at least "
            f"{cfg.min_class_labels} labelled pillars outside the held-out blocks ({held})"
        )
    return None
