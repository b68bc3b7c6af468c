"""Reviewers' corrections of a clutter run's review units, applied to a frame's membership.

A run's membership (`review_units`: per point its instance, -1 none, and the pipeline's removed
flag) is fixed once written. Reviewers correct it in the store (`app.store.clutter_corrections`),
a correction at a time, and whoever reads the membership after review (the viewer, the API,
`clutter:recompute`, the SemanticKITTI export) applies them in the order they were written:

- `remove`: the given points of an instance leave it: they belong to no instance and are kept
  (their removed flag is cleared, whatever the pipeline said), so no verdict moves them again;
- `add`: the given points that belong to no instance form a new instance (a missed object),
  whose verdict then applies to them like to any other (a reviewer adds it approved).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

REMOVE = "remove"
ADD = "add"


@dataclass(frozen=True)
class MembershipCorrection:
    """One correction of one frame: its kind, the instance, the points (indices in the frame)."""

    kind: str  # REMOVE or ADD
    instance_index: int
    points: np.ndarray  # int64, sorted, unique


def corrected_membership(
    owner: np.ndarray, flags: np.ndarray, corrections: Sequence[MembershipCorrection]
) -> tuple[np.ndarray, np.ndarray]:
    """(owner, removed flags) of a frame with `corrections` applied in order; copies, the inputs
    stay as they are. Points outside the frame are ignored (the store refuses them)."""
    owner = np.array(owner, dtype=np.int32, copy=True)
    flags = np.array(flags, dtype=bool, copy=True)
    n = len(owner)
    for c in corrections:  # a loop over corrections, each one vectorised over its points
        points = np.asarray(c.points, dtype=np.int64)
        points = points[(points >= 0) & (points < n)]
        if c.kind == REMOVE:
            mine = points[owner[points] == c.instance_index]
            owner[mine] = -1
            flags[mine] = False
        elif c.kind == ADD:
            free = points[owner[points] < 0]
            owner[free] = c.instance_index
        else:
            raise ValueError(f"unknown clutter correction kind {c.kind!r}")
    return owner, flags
