"""Versions only grow: the one conflict check of every versioned label write, and fresh ids.

A client sends the version it saw of each record it writes (pillar labels, clutter decisions,
guardrail slice labels and model decisions); the store compares them with the current versions
inside the write's transaction (`check_versions`) and refuses the whole write on any mismatch
(`StaleWriteError`, 409, with the records as they are now). That check only means "nobody
changed it since you saw it" if a version, once seen, never comes back with other content
(ABA). So:

- every step that changes a record adds one to its version: a write, an erase (a pillar label
  leaves a tombstone holding its version, `PillarTombstone`), an undo, a redo, a reset;
- rows that a run replaces wholesale (clutter instances, guardrail slices and models) get ids
  no row of their table ever had (`fresh_ids`), so an old (id, version) names no new row: a
  client holding one gets 404, never a write to something it did not see.

What "unlabelled" means to a client: version 0 is a pillar that never had a human label. A
pillar whose label was erased has no label but the tombstone's version (> 0): reads (tiles,
the 409's `current`, a write's answer) return it, and a write over the erase must send it. A
client sending 0 there never saw the erase, and is refused.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import sqlalchemy as sa
from sqlmodel import Session

from app.core.errors import StaleWriteError

NOT_CHECKED = -1  # an expected version the client did not send: not compared

_FRESH_IDS = (
    "INSERT INTO issued_id (name, last_id) VALUES (:name, {live} + :n) "
    "ON CONFLICT (name) DO UPDATE SET last_id = max(issued_id.last_id, {live}) + :n "
    "RETURNING last_id"
)


def stale(expected: Sequence[int] | np.ndarray, current: Sequence[int] | np.ndarray) -> np.ndarray:
    """Which expected versions (NOT_CHECKED: none sent) differ from the current ones."""
    expected = np.asarray(expected, dtype=np.int64)
    return (expected != NOT_CHECKED) & (expected != np.asarray(current, dtype=np.int64))


def refuse(
    keys: Sequence[int] | np.ndarray,
    expected: Sequence[int] | np.ndarray,
    current: Sequence[int] | np.ndarray,
    mask: np.ndarray,
    *,
    field: str,
    noun: str,
    states: Callable[[np.ndarray], object],
    head: str | None = None,
) -> StaleWriteError:
    """The error for the stale records `mask` picks: one line naming the field, the first stale
    record, the version it is at and the one sent; `current` is `states(stale keys)`.
    `head` replaces the line's start ("{n}" becomes the number of stale records)."""
    at = np.flatnonzero(mask)
    n = len(at)
    key = int(np.asarray(keys)[at[0]])
    sent = int(np.asarray(expected)[at[0]])
    now = int(np.asarray(current)[at[0]])
    head = (head or "{field}: {n} " + noun + "(s) changed by someone else").format(n=n, field=field)
    seen = f"not {sent}" if sent != NOT_CHECKED else "no longer as this edit left it"
    more = f" (and {n - 1} more)" if n > 1 else ""
    message = f"{head}: {noun} {key} is at version {now}, {seen}{more}; reload and retry"
    return StaleWriteError(message, states(np.asarray(keys, dtype=np.int64)[at]))


def check_versions(
    keys: Sequence[int] | np.ndarray,
    expected: Sequence[int] | np.ndarray,
    current: Sequence[int] | np.ndarray,
    *,
    field: str,
    noun: str,
    states: Callable[[np.ndarray], object],
    head: str | None = None,
) -> None:
    """Raise `StaleWriteError` (see `refuse`) when any expected version is not the current one.
    Call it inside the write's transaction, so nobody writes between the check and the write."""
    mask = stale(expected, current)
    if mask.any():
        raise refuse(
            keys, expected, current, mask, field=field, noun=noun, states=states, head=head
        )


def fresh_ids(session: Session, table: sa.Table, count: int) -> int:
    """The first of `count` consecutive ids for new rows of `table` that no row of it ever had
    (above its live rows and every id handed out here before); call it before deleting the rows
    being replaced. One statement: two writers cannot draw the same ids."""
    live = f"coalesce((SELECT max(id) FROM {table.name}), 0)"
    last = (
        session.connection()
        .execute(sa.text(_FRESH_IDS.format(live=live)), {"name": table.name, "n": int(count)})
        .scalar_one()
    )
    return int(last) - int(count) + 1
