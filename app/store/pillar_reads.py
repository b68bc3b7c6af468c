"""Pillar label reads: tiles and boxes of labels, the "uncertain first" queue, counts.

Everything that reads labels sees the human and model labels only: an erased pillar's tombstone
is no label, though a tile lists the erased pillars apart (`erased_cell_id`, `erased_version`),
the versions a write over them needs. Tile reads are built by SQLite's JSON functions, one index
range scan per grid column of the box, without a Python object per label. The writes, undo and
redo are in `app.store.pillar_labels`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime

import numpy as np
from sqlalchemy import text
from sqlmodel import Session

from app.core.errors import ConfigError
from app.store.columns import sql_time
from app.store.models import LabelSource
from app.store.pillar_labels import STORE_GRID

MAX_BOX_CELLS = 25_000_000  # 1 km x 1 km at 0.2 m: larger reads are refused


@dataclass(frozen=True)
class TileLabels:
    """Columnar labels of a box: one entry per (pillar, source)."""

    cell_id: np.ndarray
    source: np.ndarray  # str: human / model
    label: np.ndarray
    version: np.ndarray
    confidence: np.ndarray  # float, NaN for human labels
    user_id: np.ndarray  # int, -1 for none


def box_cell_ranges(x0: float, y0: float, x1: float, y1: float) -> list[tuple[int, int]]:
    """Contiguous cell-id ranges covering the box: one per grid column (ids of a column are
    consecutive in iy), so each is one index range scan."""
    if not (x1 > x0 and y1 > y0):
        raise ConfigError("box", f"x1 > x0 and y1 > y0 needed, got ({x0}, {y0}, {x1}, {y1})")
    (ix0, iy0), (ix1, iy1) = STORE_GRID.cell_index(np.array([[x0, y0], [x1, y1]]))
    if (int(ix1) - int(ix0) + 1) * (int(iy1) - int(iy0) + 1) > MAX_BOX_CELLS:  # no int64 wrap
        raise ConfigError("box", "larger than 1 km x 1 km; ask for smaller tiles")
    columns = np.arange(ix0, ix1 + 1)
    lo = STORE_GRID.cell_id(columns, np.full(len(columns), iy0))
    hi = STORE_GRID.cell_id(columns, np.full(len(columns), iy1))
    return list(zip(np.atleast_1d(lo).tolist(), np.atleast_1d(hi).tolist(), strict=True))


def _box_rows(ranges: list[tuple[int, int]], source: LabelSource | None) -> str:
    """SQL of the labels in the cell-id ranges: the ranges drive the loop (CROSS JOIN keeps
    SQLite from scanning the table once per range), each one an index range scan."""
    where = "" if source is None else f" AND p.source = '{LabelSource(source).value}'"
    return (
        "SELECT p.cell_id, p.source, p.label, p.version, p.confidence, p.user_id FROM "
        "(SELECT json_extract(value, '$[0]') AS lo, json_extract(value, '$[1]') AS hi "
        "FROM json_each(:ranges)) AS r CROSS JOIN pillar_label AS p INDEXED BY "
        f"ix_pillar_label_tile WHERE p.survey_id = :s AND p.cell_id BETWEEN r.lo AND r.hi{where}"
    )


def labels_in_box(
    session: Session,
    survey_id: int,
    box: tuple[float, float, float, float],
    source: LabelSource | None = None,
) -> TileLabels:
    """Every label (of `source`, or both) of the pillars in the world box, as arrays."""
    ranges = box_cell_ranges(*box)
    query = text(_box_rows(ranges, source))
    params = {"ranges": json.dumps(ranges), "s": survey_id}
    rows = session.connection().execute(query, params).all()
    if not rows:
        empty = np.zeros(0, dtype=np.int64)
        return TileLabels(empty, np.zeros(0, dtype="<U5"), empty, empty, np.zeros(0), empty)
    cell, src, label, version, confidence, user = zip(*rows, strict=True)
    return TileLabels(
        cell_id=np.array(cell, dtype=np.int64),
        source=np.array(src),
        label=np.array(label, dtype=np.int64),
        version=np.array(version, dtype=np.int64),
        confidence=np.array([np.nan if c is None else c for c in confidence], dtype=np.float64),
        user_id=np.array([-1 if u is None else u for u in user], dtype=np.int64),
    )


def _index_sql(shift: str) -> str:
    """SQL of a pillar's grid index from its packed id (STORE_GRID.decode)."""
    return f"((p.cell_id{shift}) & 4294967295) - 2147483648"


TILE_FIELDS = ("cell_id", "ix", "iy", "label", "source", "confidence", "version", "user_id")


def tile_json(
    session: Session,
    survey_id: int,
    box: tuple[float, float, float, float],
    source: LabelSource | None = None,
) -> str:
    """The box's labels as a columnar JSON object (one array per TILE_FIELDS entry, plus the
    grid and `count`), built by SQLite's JSON functions: no Python object per label. Pillar
    centres are origin + (index + 0.5) * cell_size; sending the integer indices instead of
    float centres halves the time to serve a tile. Erased pillars (tombstones) are no labels:
    they come apart, `erased_cell_id` / `erased_version`, the versions a write over them needs.
    """
    ranges = box_cell_ranges(*box)
    columns = {
        "cell_id": "p.cell_id",
        "ix": _index_sql(" >> 32"),
        "iy": _index_sql(""),
        "label": "p.label",
        "source": "p.source",
        "confidence": "p.confidence",
        "version": "p.version",
        "user_id": "p.user_id",
    }
    select = ", ".join(f"json_group_array({columns[f]})" for f in TILE_FIELDS)
    query = text(f"SELECT count(*), {select} FROM ({_box_rows(ranges, source)}) AS p")
    params = {"ranges": json.dumps(ranges), "s": survey_id}
    count, *arrays = session.connection().execute(query, params).one()
    body = ",".join(f'"{name}":{array}' for name, array in zip(TILE_FIELDS, arrays, strict=True))
    erased_ids, erased_versions = "[]", "[]"
    if source is None or LabelSource(source) == LabelSource.human:
        erased = session.connection().execute(text(_BOX_TOMBSTONES), params).one()
        erased_ids, erased_versions = erased
    grid = STORE_GRID
    head = f'"cell_size":{grid.cell_size!r},"origin":[{grid.origin_x!r},{grid.origin_y!r}]'
    tail = f'"erased_cell_id":{erased_ids},"erased_version":{erased_versions}'
    return f'{{{head},"count":{count},{body},{tail}}}'


# the tombstones in the box's cell-id ranges, as _box_rows reads labels
_BOX_TOMBSTONES = (
    "SELECT json_group_array(t.cell_id), json_group_array(t.version) FROM "
    "(SELECT json_extract(value, '$[0]') AS lo, json_extract(value, '$[1]') AS hi "
    "FROM json_each(:ranges)) AS r CROSS JOIN pillar_tombstone AS t "
    "WHERE t.survey_id = :s AND t.cell_id BETWEEN r.lo AND r.hi"
)


@dataclass(frozen=True)
class UncertainArea:
    x: float  # world centre of the area
    y: float
    pillars: int  # model pre-labels below the threshold with no human label
    mean_confidence: float
    cell_ids: list[int]  # the most uncertain pillars of the area, most uncertain first


def uncertain_areas(
    session: Session,
    survey_id: int,
    threshold: float = 0.9,
    area_size: float = 10.0,
    limit: int = 20,
    per_area: int = 50,
) -> list[UncertainArea]:
    """The "uncertain first" queue: areas of `area_size` metres ranked by how much unreviewed
    model doubt they hold (sum of 1 - confidence over pre-labels below `threshold` that no human
    has labelled yet)."""
    rows = (
        session.connection()
        .execute(
            text(
                "SELECT m.cell_id, m.confidence FROM pillar_label AS m "
                "WHERE m.survey_id = :s AND m.source = 'model' AND m.confidence < :t "
                "AND NOT EXISTS (SELECT 1 FROM pillar_label AS h WHERE h.survey_id = m.survey_id "
                "AND h.cell_id = m.cell_id AND h.source = 'human')"
            ),
            {"s": survey_id, "t": threshold},
        )
        .all()
    )
    if not rows:
        return []
    cells = np.array([r[0] for r in rows], dtype=np.int64)
    confidence = np.array([r[1] for r in rows], dtype=np.float64)
    ix, iy = STORE_GRID.decode(cells)
    centres = STORE_GRID.cell_center(ix, iy)
    area = np.floor(centres / area_size).astype(np.int64)
    keys, inverse = np.unique(area, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    doubt = np.bincount(inverse, weights=1.0 - confidence)
    counts = np.bincount(inverse)
    mean_conf = np.bincount(inverse, weights=confidence) / counts
    order = np.argsort(-doubt, kind="stable")[:limit]
    by_area = np.lexsort((confidence, inverse))  # grouped by area, least confident first
    starts = np.searchsorted(inverse[by_area], np.arange(len(keys)))
    result = []
    for a in order.tolist():
        members = by_area[starts[a] : starts[a] + min(int(counts[a]), per_area)]
        result.append(
            UncertainArea(
                x=float((keys[a, 0] + 0.5) * area_size),
                y=float((keys[a, 1] + 0.5) * area_size),
                pillars=int(counts[a]),
                mean_confidence=float(mean_conf[a]),
                cell_ids=cells[members].tolist(),
            )
        )
    return result


def label_counts(session: Session, survey_id: int) -> dict[str, list[int]]:
    """Pillars per class for each source."""
    rows = (
        session.connection()
        .execute(
            text(
                "SELECT source, label, count(*) FROM pillar_label WHERE survey_id = :s "
                "GROUP BY source, label"
            ),
            {"s": survey_id},
        )
        .all()
    )
    counts = {s.value: [0, 0, 0, 0] for s in LabelSource}
    for source, label, n in rows:
        counts[source][int(label)] = int(n)
    return counts


def reviewed_class_counts(session: Session, survey_id: int) -> np.ndarray:
    """(4,) pillars per class over the pillars a phantom run judged (its model pre-labels), each
    counted with its human label where a person gave one: the survey's class shares as reviewed
    so far (retraining's class priors)."""
    rows = (
        session.connection()
        .execute(
            text(
                "SELECT coalesce(h.label, m.label), count(*) FROM pillar_label AS m "
                "LEFT JOIN pillar_label AS h ON h.survey_id = m.survey_id "
                "AND h.cell_id = m.cell_id AND h.source = 'human' "
                "WHERE m.survey_id = :s AND m.source = 'model' GROUP BY 1"
            ),
            {"s": survey_id},
        )
        .all()
    )
    counts = np.zeros(4, dtype=np.int64)
    for label, n in rows:
        counts[int(label)] += int(n)
    return counts


def human_labels_since(session: Session, since: datetime | None) -> int:
    """Human labels written (created or changed) after `since`, all surveys: the retraining
    trigger counts these."""
    query = "SELECT count(*) FROM pillar_label WHERE source = 'human'"
    params: dict = {}
    if since is not None:
        query += " AND updated_at > :since"
        params["since"] = sql_time(since)
    return int(session.connection().execute(text(query), params).scalar_one())
