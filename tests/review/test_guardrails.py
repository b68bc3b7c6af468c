"""The guardrail review helpers on a run of the simulated street (`jobs` fixture)."""

from __future__ import annotations

import numpy as np

from app.review.guardrails import preview_correction
from app.store.guardrail_review import slice_table
from tests.jobs.guardrail_street import Jobs


def test_preview_correction_fills_a_gap_without_saving(jobs: Jobs) -> None:
    jobs.run()
    with jobs.session() as session:
        table = slice_table(session, jobs.survey_id)
        on = np.flatnonzero(table.label == 1)
        # one guardrail slice in the middle of a run set to "other" is filled back in
        middle = on[len(on) // 4]
        preview = preview_correction(session, jobs.survey_id, {int(table.id[middle]): 0})
        entry = next(s for s in preview["slices"] if s["id"] == table.id[middle])
        assert entry["proposed"] == 0 and entry["corrected_label"] == 1
        assert slice_table(session, jobs.survey_id).label[middle] == 1  # nothing saved
