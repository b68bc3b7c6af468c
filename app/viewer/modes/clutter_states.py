"""What the clutter review shows of one frame: each point's state with the reviewers' decisions
applied, its colour, and the store's instances of the frame (with the run folder they came
from)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from app.store import clutter_corrections, clutter_review
from app.store.clutter_review import InstanceState
from app.store.models import Decision

if TYPE_CHECKING:
    from app.viewer.session import ViewerSession

# point states in the 3D view and on the image
KEPT, KEPT_PENDING, REMOVED_PENDING, APPROVED, REJECTED = range(5)
STATE_RGB = np.array(
    [
        (150, 150, 150),  # kept: not part of any instance
        (150, 150, 150),  # kept: an instance's point the pipeline keeps (pending)
        (255, 150, 0),  # removed: pending, the pipeline's flag
        (230, 30, 30),  # removed: approved
        (40, 200, 80),  # kept: rejected
    ],
    dtype=np.uint8,
)
SELECTED_RGB = np.array((255, 0, 255), dtype=np.uint8)  # apart from every state colour
LEGEND = (
    ("removed (pending: pipeline)", REMOVED_PENDING),
    ("removed (approved)", APPROVED),
    ("kept (rejected)", REJECTED),
    ("kept", KEPT),
)


def point_states(
    owner: np.ndarray, flags: np.ndarray, index: np.ndarray, decision: Sequence[Decision]
) -> np.ndarray:
    """(N,) state of each point of a frame (KEPT ... REJECTED) with the decisions applied:
    approved -> removed, rejected -> kept, pending -> the pipeline's flag (as recompute does)."""
    verdict = np.array(
        [{Decision.approved: 1, Decision.rejected: 0}.get(Decision(d), -1) for d in decision],
        dtype=np.int8,
    )
    size = max(int(owner.max(initial=-1)), int(np.max(index, initial=-1))) + 1
    table = np.full(size, -1, dtype=np.int8)
    table[np.asarray(index, dtype=np.int64)] = verdict
    flags = np.asarray(flags, dtype=bool)
    state = np.where(flags, REMOVED_PENDING, KEPT).astype(np.int8)
    owned = owner >= 0
    choice = table[owner[owned]]
    cases = [choice == 1, choice == 0, flags[owned]]
    state[owned] = np.select(cases, [APPROVED, REJECTED, REMOVED_PENDING], KEPT_PENDING)
    return state


def state_colors(state: np.ndarray, z: np.ndarray, selected: np.ndarray | None) -> np.ndarray:
    """(n, 3) uint8: state colours, kept points shaded by height, the selected instance magenta
    (its state is in the list)."""
    rgb = STATE_RGB[state].astype(np.float32)
    kept = (state == KEPT) | (state == KEPT_PENDING)
    if kept.any() and len(z):
        lo, hi = np.percentile(z, [2, 98])
        shade = np.clip((z[kept] - lo) / max(hi - lo, 1e-3), 0.0, 1.0)
        rgb[kept] *= (0.55 + 0.6 * shade)[:, None]
    if selected is not None and selected.any():
        rgb[selected] = SELECTED_RGB
    return np.clip(rgb, 0, 255).astype(np.uint8)


def run_folder(session: ViewerSession, survey_id: int) -> Path | None:
    """The folder of the clutter run whose instances the store holds (None: no run yet)."""
    with session.db() as db:
        return clutter_corrections.current_run_folder(db, survey_id)


def frame_instances(session: ViewerSession, survey_id: int, frame_id: str) -> list[InstanceState]:
    """Every instance of one frame with its decision and version (all pages)."""
    out: list[InstanceState] = []
    with session.db() as db:
        while True:
            total, page = clutter_review.list_instances(
                db, survey_id, frame_id=frame_id, offset=len(out), limit=clutter_review.MAX_PAGE
            )
            out += page
            if not page or len(out) >= total:
                return out
