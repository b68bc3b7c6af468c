"""Pillar labels: versioned batch writes and per-user undo / redo (reads: `pillar_reads`).

Every survey's labels live on ONE world-aligned grid (`STORE_GRID`: origin (0, 0), 0.2 m cells,
the phantom paper's pillar size), so a pillar keeps its id across pipeline runs, tiles and
re-imports. A pillar has at most one human label and one model pre-label (`source`).

Writes are batches: one labelling action (brush stroke, rectangle) = one `PillarEditBatch` with
each pillar's human label before and after, written in one transaction with plain SQL
(`INSERT ... ON CONFLICT DO UPDATE` through executemany: 10,000 labels take tens of ms, where
one ORM object per label takes seconds). A batch may carry the version each pillar had when the
client read it; any mismatch rejects the whole batch with the current state of those pillars.
Undo reverts the user's newest done batch, redo re-applies their most recently undone one; a new
batch makes the undone ones unredoable, as in every editor.

Versions only grow (`app.store.versions`): every write, erase, undo and redo adds one to each
pillar it touches. An erase deletes the label row and leaves a tombstone (`pillar_tombstone`)
with the new version, so everything that reads labels (tiles' labels, counts, exports, training
data, the retraining trigger, the viewer's colours) never sees it, while version checks and
answers do: a tile lists the erased pillars apart (`erased_cell_id`, `erased_version`). Undo /
redo check versions too: each edit keeps the version its last step left (`version`, which its
next undo / redo expects) and the one that step replaced (`version_before`, whose content the
next step restores; edits that expected that version then expect the restored one).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

import numpy as np
from sqlalchemy import text
from sqlmodel import Session

from app.core.errors import ConfigError, ConflictError
from app.core.labels import PillarClass
from app.geometry.pillars import PillarGrid
from app.store.audit import audit
from app.store.columns import sql_time
from app.store.db import commit, write_transaction
from app.store.models import EditState, PillarEditBatch, utcnow
from app.store.versions import NOT_CHECKED, check_versions, refuse, stale

STORE_GRID = PillarGrid(0.0, 0.0, 0.2)  # s_c = 0.2 m (Nagy & Benedek)
NO_LABEL = -1  # "no human label" in before/after arrays

# Batch statements read their rows from one JSON array parameter (`json_each`), so a 10,000-label
# batch is one statement executed in C instead of 10,000 parameter sets built in Python.
_UPSERT = text(
    """INSERT INTO pillar_label
        (survey_id, cell_id, label, source, confidence, user_id, model_version_id, version,
         created_at, updated_at)
    SELECT :survey_id, json_extract(value, '$[0]'), json_extract(value, '$[1]'), 'human', NULL,
        :user_id, NULL, json_extract(value, '$[2]'), :now, :now
    FROM json_each(:rows) WHERE true
    ON CONFLICT (survey_id, cell_id, source) DO UPDATE SET
        label = excluded.label,
        user_id = excluded.user_id,
        version = excluded.version,
        updated_at = excluded.updated_at"""
)
_DELETE = text(
    "DELETE FROM pillar_label WHERE survey_id = :survey_id AND source = 'human' "
    "AND cell_id IN (SELECT value FROM json_each(:ids))"
)
_BURY = text(
    """INSERT INTO pillar_tombstone (survey_id, cell_id, version, user_id, updated_at)
    SELECT :survey_id, json_extract(value, '$[0]'), json_extract(value, '$[1]'), :user_id, :now
    FROM json_each(:rows) WHERE true
    ON CONFLICT (survey_id, cell_id) DO UPDATE SET
        version = excluded.version,
        user_id = excluded.user_id,
        updated_at = excluded.updated_at"""
)
_UNBURY = text(
    "DELETE FROM pillar_tombstone WHERE survey_id = :survey_id "
    "AND cell_id IN (SELECT value FROM json_each(:ids))"
)
_RECORD_EDITS = text(
    "INSERT INTO pillar_edit (batch_id, cell_id, before_label, after_label, version_before, "
    "version) SELECT :batch, json_extract(value, '$[0]'), "
    "nullif(json_extract(value, '$[1]'), -1), nullif(json_extract(value, '$[2]'), -1), "
    "json_extract(value, '$[3]'), json_extract(value, '$[4]') FROM json_each(:rows)"
)
# an undo / redo restored the content of version $[1] of pillar $[0] as version $[2]: the
# survey's edits that expected $[1] expect $[2] now
_RESTORED = text(
    "UPDATE pillar_edit SET version = json_extract(n.value, '$[2]') FROM json_each(:rows) AS n "
    "WHERE pillar_edit.cell_id = json_extract(n.value, '$[0]') "
    "AND pillar_edit.version = json_extract(n.value, '$[1]') "
    "AND pillar_edit.batch_id IN (SELECT id FROM pillar_edit_batch WHERE survey_id = :s)"
)
# a batch's undo / redo went through: each pillar was at its edit's version (checked) and is
# one above it now
_STEPPED = text(
    "UPDATE pillar_edit SET version_before = version, version = version + 1 "
    "WHERE batch_id = :b AND version IS NOT NULL"
)
# the same for edits from before schema version 4 (no version: checked by label)
_STEPPED_LEGACY = text(
    "UPDATE pillar_edit SET version_before = json_extract(n.value, '$[1]'), "
    "version = json_extract(n.value, '$[2]') FROM json_each(:rows) AS n "
    "WHERE pillar_edit.id = json_extract(n.value, '$[0]')"
)
# a pillar's human label, or its tombstone (label -1 / NULL) when it was erased
_IN_IDS = "survey_id = :s AND cell_id IN (SELECT value FROM json_each(:ids))"
_HUMAN_COLUMNS = text(
    "SELECT json_group_array(cell_id), json_group_array(label), json_group_array(version) FROM "
    f"(SELECT cell_id, label, version FROM pillar_label WHERE source = 'human' AND {_IN_IDS} "
    f"UNION ALL SELECT cell_id, -1, version FROM pillar_tombstone WHERE {_IN_IDS})"
)
_CURRENT_HUMAN = text(
    "SELECT cell_id, label, version, user_id, updated_at FROM pillar_label "
    f"WHERE source = 'human' AND {_IN_IDS} "
    f"UNION ALL SELECT cell_id, NULL, version, user_id, updated_at FROM pillar_tombstone "
    f"WHERE {_IN_IDS}"
)


@dataclass(frozen=True)
class LabelWrite:
    """What a batch did: its id and, per pillar in request order, the new version (an erase's
    too: versions only grow)."""

    batch_id: int | None
    cell_ids: np.ndarray
    versions: np.ndarray


def _ids_json(cell_ids: np.ndarray) -> str:
    return json.dumps(np.asarray(cell_ids, dtype=np.int64).tolist())


def current_human(session: Session, survey_id: int, cell_ids: np.ndarray) -> dict[int, tuple]:
    """cell_id -> (label, version, user_id, updated_at) of the pillars' current human labels;
    label None for an erased one (its tombstone: version and who erased it when)."""
    params = {"s": survey_id, "ids": _ids_json(cell_ids)}
    rows = session.connection().execute(_CURRENT_HUMAN, params).all()
    return {int(r[0]): (None if r[1] is None else int(r[1]), int(r[2]), r[3], r[4]) for r in rows}


def human_columns(
    session: Session, survey_id: int, cell_ids: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(label, version) of each pillar's human label, NO_LABEL where it has none (version: the
    erase's, 0 if it never had one): one row of JSON arrays built by SQLite, no Python object
    per label. `cell_ids` must be unique."""
    cell_ids = np.asarray(cell_ids, dtype=np.int64)
    query = session.connection().execute(
        _HUMAN_COLUMNS, {"s": survey_id, "ids": _ids_json(cell_ids)}
    )
    found, found_labels, found_versions = (np.array(json.loads(a), np.int64) for a in query.one())
    order = np.argsort(cell_ids)
    at = order[np.searchsorted(cell_ids[order], found)]
    labels = np.full(len(cell_ids), NO_LABEL, dtype=np.int64)
    versions = np.zeros(len(cell_ids), dtype=np.int64)
    labels[at], versions[at] = found_labels, found_versions
    return labels, versions


def _stale(session: Session, survey_id: int, cell_ids: np.ndarray) -> list[dict]:
    """The current state of these pillars, for a StaleWriteError."""
    current = current_human(session, survey_id, cell_ids)
    return [_state(c, current.get(c)) for c in np.asarray(cell_ids).tolist()]


def _state(cell_id: int, row: tuple | None) -> dict:
    if row is None:
        return {"cell_id": cell_id, "label": None, "version": 0, "user_id": None}
    label, version, user_id, updated_at = row
    return {
        "cell_id": cell_id,
        "label": label,
        "version": version,
        "user_id": user_id,
        "updated_at": str(updated_at),
    }


def validate_batch(cell_ids: np.ndarray, labels: np.ndarray) -> None:
    if len(cell_ids) != len(labels):
        raise ConfigError("labels", "cell_ids and labels differ in length")
    bad = (labels != NO_LABEL) & ((labels < 0) | (labels > int(PillarClass.phantom)))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ConfigError(f"labels[{i}].label", f"must be 0-3 or null, got {int(labels[i])}")
    unique, counts = np.unique(cell_ids, return_counts=True)
    if (counts > 1).any():
        raise ConfigError("labels", f"cell_id {int(unique[counts > 1][0])} appears twice")


def _apply(
    session: Session,
    survey_id: int,
    user_id: int | None,
    cell_ids: np.ndarray,
    before: np.ndarray,
    versions_before: np.ndarray,
    labels: np.ndarray,
    now: datetime,
) -> np.ndarray:
    """Set (label >= 0) or erase (NO_LABEL) the human labels, each pillar one version up: an
    erase leaves a tombstone, a label replaces one. No checks. Returns the versions after
    (exact inside the write's transaction, where `before` / `versions_before` were read)."""
    versions = versions_before + 1
    conn = session.connection()
    keep = labels != NO_LABEL
    params = {"survey_id": survey_id, "user_id": user_id, "now": sql_time(now)}
    if keep.any():
        rows = np.stack([cell_ids[keep], labels[keep], versions[keep]], axis=1)
        conn.execute(_UPSERT, {**params, "rows": json.dumps(rows.tolist())})
        buried = keep & (before == NO_LABEL) & (versions_before > 0)
        if buried.any():
            conn.execute(_UNBURY, {"survey_id": survey_id, "ids": _ids_json(cell_ids[buried])})
    if (~keep).any():
        rows = np.stack([cell_ids[~keep], versions[~keep]], axis=1)
        conn.execute(_BURY, {**params, "rows": json.dumps(rows.tolist())})
        labelled = ~keep & (before != NO_LABEL)
        if labelled.any():
            conn.execute(_DELETE, {"survey_id": survey_id, "ids": _ids_json(cell_ids[labelled])})
    return versions


def write_labels(
    session: Session,
    survey_id: int,
    user_id: int | None,
    cell_ids: Sequence[int] | np.ndarray,
    labels: Sequence[int] | np.ndarray,
    expected_versions: Sequence[int | None] | None = None,
) -> LabelWrite:
    """Write one batch of human labels (NO_LABEL erases) as one undoable action; commits.

    `expected_versions[i]` (optional, None = don't check) is the version the client saw: 0
    means "never labelled", an erased pillar is at its erase's version. A mismatch anywhere
    raises `StaleWriteError` carrying the current state of every stale pillar, and nothing is
    written.
    """
    cell_ids = np.asarray(cell_ids, dtype=np.int64).ravel()
    labels = np.asarray(labels, dtype=np.int64).ravel()
    validate_batch(cell_ids, labels)
    if len(cell_ids) == 0:
        return LabelWrite(None, cell_ids, np.zeros(0, dtype=np.int64))
    with write_transaction(session):  # the check, the undo record's "before" and the write
        before, versions_before = human_columns(session, survey_id, cell_ids)
        if expected_versions is not None:
            if len(expected_versions) != len(cell_ids):
                raise ConfigError("versions", "one expected version (or None) per pillar needed")
            expected = [NOT_CHECKED if v is None else v for v in expected_versions]
            check_versions(
                cell_ids,
                expected,
                versions_before,
                field="versions",
                noun="pillar",
                states=lambda stale_ids: _stale(session, survey_id, stale_ids),
            )
        now = utcnow()
        versions = _apply(
            session, survey_id, user_id, cell_ids, before, versions_before, labels, now
        )
        batch = _record_batch(
            session, survey_id, user_id, cell_ids, before, labels, versions_before, versions
        )
        classes = np.bincount(labels[labels != NO_LABEL], minlength=4).tolist()
        audit(
            session,
            user_id,
            "pillar.label",
            "pillar_edit_batch",
            batch.id,
            survey_id=survey_id,
            pillars=len(cell_ids),
            per_class=classes,
            erased=int((labels == NO_LABEL).sum()),
        )
        commit(session)
        return LabelWrite(batch.id, cell_ids, versions)


def _record_batch(
    session: Session,
    survey_id: int,
    user_id: int | None,
    cell_ids: np.ndarray,
    before: np.ndarray,
    after: np.ndarray,
    versions_before: np.ndarray,
    versions: np.ndarray,
) -> PillarEditBatch:
    """The undo record; the user's undone batches stop being redoable."""
    conn = session.connection()
    conn.execute(
        text(
            "UPDATE pillar_edit_batch SET state = 'discarded' WHERE survey_id = :s "
            "AND user_id IS :u AND state = 'undone'"
        ),
        {"s": survey_id, "u": user_id},
    )
    batch = PillarEditBatch(survey_id=survey_id, user_id=user_id, size=len(cell_ids))
    session.add(batch)
    session.flush()
    columns = [cell_ids, before, after, versions_before, versions]  # NO_LABEL -> NULL in SQL
    rows = np.stack(columns, axis=1).tolist()
    conn.execute(_RECORD_EDITS, {"batch": batch.id, "rows": json.dumps(rows)})
    return batch


@dataclass(frozen=True)
class _Edits:
    """A batch's edits as columns (NO_LABEL / NOT_CHECKED where the store holds NULL)."""

    id: np.ndarray
    cell: np.ndarray
    before: np.ndarray
    after: np.ndarray
    version_before: np.ndarray
    version: np.ndarray


def _batch_edits(session: Session, batch_id: int) -> _Edits:
    query = session.connection().execute(
        text(
            "SELECT json_group_array(id), json_group_array(cell_id), "
            "json_group_array(coalesce(before_label, -1)), "
            "json_group_array(coalesce(after_label, -1)), "
            "json_group_array(coalesce(version_before, -1)), "
            "json_group_array(coalesce(version, -1)) FROM "
            "(SELECT * FROM pillar_edit WHERE batch_id = :b ORDER BY id)"
        ),
        {"b": batch_id},
    )
    return _Edits(*(np.array(json.loads(a), dtype=np.int64) for a in query.one()))


def _step(session: Session, survey_id: int, user_id: int | None, undo: bool) -> LabelWrite:
    """Undo the newest done batch, or redo the most recently undone one. Each of its pillars
    must still be at the version the batch's last step left (edits from before schema version
    4 have none: their label must be the one it left)."""
    state, order = (EditState.done, "DESC") if undo else (EditState.undone, "ASC")
    with write_transaction(session):  # nobody changed the pillars since? then the write
        row = (
            session.connection()
            .execute(
                text(
                    f"SELECT id FROM pillar_edit_batch WHERE survey_id = :s AND user_id IS :u "
                    f"AND state = :state ORDER BY id {order} LIMIT 1"
                ),
                {"s": survey_id, "u": user_id, "state": state.value},
            )
            .first()
        )
        what = "undo" if undo else "redo"
        if row is None:
            raise ConflictError(f"nothing to {what} for this user on survey {survey_id}")
        batch = session.get(PillarEditBatch, int(row[0]))
        edits = _batch_edits(session, batch.id)
        expected, target = (edits.after, edits.before) if undo else (edits.before, edits.after)
        now_labels, now_versions = human_columns(session, survey_id, edits.cell)
        legacy = edits.version == NOT_CHECKED
        changed = stale(edits.version, now_versions) | (legacy & (now_labels != expected))
        if changed.any():
            raise refuse(
                edits.cell,
                edits.version,
                now_versions,
                changed,
                field="versions",
                noun="pillar",
                states=lambda stale_ids: _stale(session, survey_id, stale_ids),
                head=f"cannot {what}: {{n}} of its pillar labels were changed since",
            )
        versions = _apply(
            session, survey_id, user_id, edits.cell, now_labels, now_versions, target, utcnow()
        )
        _restore_versions(session, survey_id, batch.id, edits, now_versions, versions)
        batch.state = EditState.undone if undo else EditState.done
        session.add(batch)
        audit(
            session,
            user_id,
            f"pillar.{what}",
            "pillar_edit_batch",
            batch.id,
            pillars=len(edits.cell),
        )
        commit(session)
        return LabelWrite(batch.id, edits.cell, versions)


def _restore_versions(
    session: Session,
    survey_id: int,
    batch_id: int,
    edits: _Edits,
    replaced: np.ndarray,
    versions: np.ndarray,
) -> None:
    """After an undo / redo of `edits`: the edits that expected the version whose content it
    restored expect the new one; the batch's own edits remember what they replaced and left."""
    conn = session.connection()
    known = edits.version_before > 0
    if known.any():
        rows = np.stack([edits.cell[known], edits.version_before[known], versions[known]], axis=1)
        conn.execute(_RESTORED, {"s": survey_id, "rows": json.dumps(rows.tolist())})
    conn.execute(_STEPPED, {"b": batch_id})
    legacy = edits.version == NOT_CHECKED
    if legacy.any():
        rows = np.stack([edits.id[legacy], replaced[legacy], versions[legacy]], axis=1)
        conn.execute(_STEPPED_LEGACY, {"rows": json.dumps(rows.tolist())})


def undo(session: Session, survey_id: int, user_id: int | None) -> LabelWrite:
    return _step(session, survey_id, user_id, undo=True)


def redo(session: Session, survey_id: int, user_id: int | None) -> LabelWrite:
    return _step(session, survey_id, user_id, undo=False)
