"""Guardrail review helpers: the adjacency-correction preview and a slice's world position
(answered at once to the API and the viewer), and the last run's saved slice stage that they
and `guardrail:rebuild` read."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from sqlmodel import Session

from app.core.errors import ConfigError, ConflictError, NotFoundError
from app.pipelines.guardrail.correction import correct_labels
from app.pipelines.guardrail.pipeline import ReconstructionInput, StoredStage, confident
from app.store.guardrail_review import slice_table, trajectory_position
from app.store.guardrail_runs import GuardrailRun, latest_run, match_slices
from app.store.models import GuardrailSlice
from app.store.surveys import get_survey


def load_stage(
    run: GuardrailRun, slices_only: bool = False, points_of: np.ndarray | None = None
) -> ReconstructionInput:
    """The slice stage `run` saved (slices, features, config): what a rebuild or a preview
    starts from (`ReconstructionInput.load`: `points_of` the slices whose points are read)."""
    with reading_stage(run) as path:
        return ReconstructionInput.load(path, slices_only=slices_only, points_of=points_of)


def stage_sample(run: GuardrailRun, cap: int) -> tuple[ReconstructionInput, np.ndarray, np.ndarray]:
    """The slices `run` saved (without points), and (xyz, slice of each) of at most `cap` of
    their points, evenly spread, read part by part (`StoredStage.sampled`)."""
    with reading_stage(run) as path:
        stage = StoredStage.open(path)
        return stage.index, *stage.sampled(cap)


@contextmanager
def reading_stage(run: GuardrailRun) -> Iterator[Path]:
    """The path of the slice stage `run` saved; a file of it missing while it is read is a 409
    that says to run it again (a rebuild reads its parts guardrail by guardrail)."""
    path = Path(run.stage_path)
    try:
        yield path
    except FileNotFoundError as exc:
        missing = exc.filename or path
        raise ConflictError(
            f"{missing}: the slice stage of the last guardrail run is missing; run it again"
        ) from None


def current_run(session: Session, survey_id: int) -> GuardrailRun:
    """The survey's last guardrail run; 409 when it has none."""
    get_survey(session, survey_id)
    run = latest_run(session, survey_id)
    if run is None:
        raise ConflictError(f"survey {survey_id} has no guardrail run yet; run run:guardrail")
    return run


def stage_rows(saved: ReconstructionInput, component: np.ndarray, index: np.ndarray) -> np.ndarray:
    """For each store slice, its slice in the saved stage (the two must be the same set)."""
    s = saved.slices
    at = match_slices(component, index, s.component, s.station_index)
    if len(component) != len(s) or (at < 0).any():
        raise ConflictError(
            "the survey's slices no longer match the last guardrail run's stage; run it again"
        )
    return at


def preview_correction(
    session: Session,
    survey_id: int,
    labels: dict[int, int],
    max_gap: int | None = None,
    max_isolated: int | None = None,
) -> dict[str, Any]:
    """The adjacency correction of the last run applied to the survey's labels with `labels`
    (slice id -> 0/1) put in, nothing saved. Input per slice: the given label, else the human
    label, else the classifier's raw label. Answers every slice whose corrected label differs
    from its current label, plus the given ones."""
    run = current_run(session, survey_id)
    table = slice_table(session, survey_id)
    by_id = np.argsort(table.id)
    sorted_ids = table.id[by_id]
    ids = np.fromiter(labels.keys(), dtype=np.int64, count=len(labels))
    given = np.fromiter(labels.values(), dtype=np.int64, count=len(labels))
    pos = np.clip(np.searchsorted(sorted_ids, ids), 0, max(len(sorted_ids) - 1, 0))
    found = sorted_ids[pos] == ids if len(sorted_ids) else np.zeros(len(ids), dtype=bool)
    if not found.all():
        raise NotFoundError(f"guardrail slice {ids[~found][0]} not found in survey {survey_id}")
    if not np.isin(given, (0, 1)).all():
        raise ConfigError("labels", "every label must be 0 or 1")
    rows = by_id[pos] if len(ids) else np.zeros(0, dtype=np.int64)
    proposed = np.where(table.human, table.label, table.predicted)
    proposed[rows] = given
    saved = load_stage(run, slices_only=True)
    at = stage_rows(saved, table.component, table.slice_index)
    stage_labels = np.zeros(len(saved.slices), dtype=np.int64)
    stage_labels[at] = proposed
    gap = saved.config.max_gap if max_gap is None else max_gap
    isolated = saved.config.max_isolated if max_isolated is None else max_isolated
    keep = np.zeros(len(saved.slices), dtype=bool)
    sure = confident(table.probability, saved.config.keep_confident)
    if sure is not None:
        keep[at] = sure
    corrected = correct_labels(
        saved.slices, stage_labels, max_gap=gap, max_isolated=isolated, keep=keep
    )[at]
    show = corrected != table.label
    show[rows] = True
    pick = np.flatnonzero(show)
    return {
        "max_gap": gap,
        "max_isolated": isolated,
        "guardrail_slices": int(corrected.sum()),
        "changed": int((corrected != table.label).sum()),
        "slices": [
            {
                "id": int(i),
                "component_id": int(c),
                "slice_index": int(k),
                "label": int(lab),
                "proposed": int(p),
                "corrected_label": int(q),
            }
            for i, c, k, lab, p, q in zip(
                table.id[pick],
                table.component[pick],
                table.slice_index[pick],
                table.label[pick],
                proposed[pick],
                corrected[pick],
                strict=True,
            )
        ],  # fmt: skip
    }


def slice_position(session: Session, survey_id: int, row: GuardrailSlice) -> list[float] | None:
    """World position of a slice: the centre of its points from the last run's stage, else the
    sensor position at its station."""
    run = latest_run(session, survey_id)
    if run is not None and Path(run.stage_path).is_file():
        s = ReconstructionInput.load(Path(run.stage_path), slices_only=True).slices
        at = match_slices(
            np.array([row.component_id]), np.array([row.slice_index]), s.component, s.station_index
        )
        if at[0] >= 0:
            return [float(v) for v in s.centre[at[0]]]
    return trajectory_position(session, survey_id, row.station_m)
