"""Pillar label operations on a real SQLite file: batches, versions, undo / redo, tiles."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

import app.store.pillar_labels as pillar_labels
from app.core.errors import ConfigError, ConflictError, StaleWriteError
from app.store.models import AuditEvent, LabelSource, PillarLabel, Survey, User
from app.store.pillar_labels import NO_LABEL, STORE_GRID, redo, undo, write_labels
from app.store.pillar_reads import (
    box_cell_ranges,
    human_labels_since,
    label_counts,
    labels_in_box,
    tile_json,
    uncertain_areas,
)


@pytest.fixture
def ids(session: Session) -> dict[str, int]:
    survey = Survey(name="s", format="sim", source_path="/s")
    anna, bob = (
        User(username="anna", hashed_password="x"),
        User(username="bob", hashed_password="x"),
    )
    session.add_all([survey, anna, bob])
    session.commit()
    return {"survey": survey.id, "anna": anna.id, "bob": bob.id}


def cells(xy: list[tuple[float, float]]) -> np.ndarray:
    ix, iy = STORE_GRID.cell_index(np.array(xy)).T
    return STORE_GRID.cell_id(ix, iy)


def human(session: Session, survey: int) -> dict[int, int]:
    rows = session.exec(
        select(PillarLabel).where(
            PillarLabel.survey_id == survey, PillarLabel.source == LabelSource.human
        )
    ).all()
    return {r.cell_id: r.label for r in rows}


def test_batch_write_sets_labels_versions_and_audit(session: Session, ids: dict) -> None:
    c = cells([(1.0, 1.0), (1.3, 1.0), (-5.0, 7.0)])
    first = write_labels(session, ids["survey"], ids["anna"], c, [3, 3, 0])
    assert first.versions.tolist() == [1, 1, 1]
    second = write_labels(session, ids["survey"], ids["bob"], c[:1], [1])
    assert second.versions.tolist() == [2]
    assert human(session, ids["survey"]) == {c[0]: 1, c[1]: 3, c[2]: 0}
    row = session.exec(select(PillarLabel).where(PillarLabel.cell_id == int(c[0]))).one()
    assert row.user_id == ids["bob"]
    events = session.exec(select(AuditEvent).where(AuditEvent.action == "pillar.label")).all()
    assert [e.user_id for e in events] == [ids["anna"], ids["bob"]]
    assert events[0].payload["per_class"] == [1, 0, 0, 2]


def test_stale_version_rejects_the_whole_batch(session: Session, ids: dict) -> None:
    c = cells([(1.0, 1.0), (2.0, 2.0)])
    write_labels(session, ids["survey"], ids["anna"], c[:1], [3])
    with pytest.raises(StaleWriteError) as caught:
        write_labels(session, ids["survey"], ids["bob"], c, [0, 0], expected_versions=[0, 0])
    assert caught.value.current == [
        {**caught.value.current[0], "cell_id": int(c[0]), "label": 3, "version": 1}
    ]
    assert human(session, ids["survey"]) == {c[0]: 3}  # nothing of the batch was written
    ok = write_labels(session, ids["survey"], ids["bob"], c, [0, 0], expected_versions=[1, 0])
    assert ok.versions.tolist() == [2, 1]


def test_invalid_batches_name_the_field(session: Session, ids: dict) -> None:
    with pytest.raises(ConfigError, match=r"labels\[1\].label: must be 0-3"):
        write_labels(session, ids["survey"], ids["anna"], [1, 2], [0, 7])
    with pytest.raises(ConfigError, match="cell_id 5 appears twice"):
        write_labels(session, ids["survey"], ids["anna"], [5, 5], [0, 1])


def test_undo_redo_are_per_user_and_a_new_edit_clears_redo(session: Session, ids: dict) -> None:
    s, anna, bob = ids["survey"], ids["anna"], ids["bob"]
    a, b, c = cells([(0.1, 0.1), (0.5, 0.1), (9.0, 9.0)])
    write_labels(session, s, anna, [a, b], [3, 3])
    write_labels(session, s, anna, [a], [1])
    write_labels(session, s, bob, [c], [2])
    assert human(session, s) == {a: 1, b: 3, c: 2}
    undone = undo(session, s, anna)  # anna's newest: a 3 -> 1 reverted, bob's untouched
    assert human(session, s) == {a: 3, b: 3, c: 2}
    assert undone.cell_ids.tolist() == [a] and undone.versions.tolist() == [3]
    undone = undo(session, s, anna)
    assert human(session, s) == {c: 2}
    assert undone.versions.tolist() == [4, 2]  # erased: versions only grow
    with pytest.raises(ConflictError, match="nothing to undo"):
        undo(session, s, anna)
    assert redo(session, s, anna).versions.tolist() == [5, 3]
    assert human(session, s) == {a: 3, b: 3, c: 2}
    assert redo(session, s, anna).versions.tolist() == [6]
    assert human(session, s) == {a: 1, b: 3, c: 2}
    undo(session, s, anna)
    erased = write_labels(session, s, anna, [b], [NO_LABEL])  # erase: a new action
    assert erased.versions.tolist() == [4]
    with pytest.raises(ConflictError, match="nothing to redo"):
        redo(session, s, anna)
    assert human(session, s) == {a: 3, c: 2}


def test_undo_refuses_when_someone_changed_the_pillars_since(session: Session, ids: dict) -> None:
    s = ids["survey"]
    (a,) = cells([(3.0, 3.0)])
    write_labels(session, s, ids["anna"], [a], [3])
    write_labels(session, s, ids["bob"], [a], [0])
    with pytest.raises(StaleWriteError, match="cannot undo: 1 of its pillar labels"):
        undo(session, s, ids["anna"])
    assert human(session, s) == {a: 0}


def test_the_version_check_and_the_write_are_one_transaction(
    engine: Engine, ids: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two writers that both saw version 1: the one that checks second must see the first's
    write, even when it checks while the first is between its check and its write."""
    s = ids["survey"]
    (a,) = cells([(4.0, 4.0)])
    with Session(engine) as session:
        write_labels(session, s, ids["anna"], [a], [3])
    checked, release = threading.Event(), threading.Event()
    apply = pillar_labels._apply

    def slow_apply(*args, **kwargs):  # anna's write pauses after her check passed
        if threading.current_thread().name == "anna":
            checked.set()
            release.wait(10)
        return apply(*args, **kwargs)

    monkeypatch.setattr(pillar_labels, "_apply", slow_apply)
    outcome: dict[str, str] = {}

    def writer(user: str, label: int) -> None:
        try:
            with Session(engine) as session:
                write_labels(session, s, ids[user], [a], [label], expected_versions=[1])
            outcome[user] = "written"
        except StaleWriteError:
            outcome[user] = "stale"

    anna = threading.Thread(target=writer, args=("anna", 1), name="anna")
    anna.start()
    assert checked.wait(10)
    bob = threading.Thread(target=writer, args=("bob", 2), name="bob")
    bob.start()
    bob.join(0.5)  # before the fix bob wrote here, then anna overwrote him unseen
    release.set()
    anna.join(10)
    bob.join(10)
    assert outcome == {"anna": "written", "bob": "stale"}
    with Session(engine) as session:
        assert human(session, s) == {a: 1}
        query = select(PillarLabel.version).where(PillarLabel.cell_id == int(a))
        assert session.exec(query).all() == [2]


def test_a_refused_write_does_not_keep_the_write_lock(engine: Engine, ids: dict) -> None:
    s = ids["survey"]
    (a,) = cells([(5.0, 5.0)])
    with Session(engine) as first, Session(engine) as second:
        write_labels(first, s, ids["anna"], [a], [3])
        with pytest.raises(StaleWriteError):
            write_labels(first, s, ids["anna"], [a], [0], expected_versions=[0])
        with pytest.raises(ConflictError, match="nothing to redo"):
            redo(first, s, ids["anna"])
        # `first` stays open: had it kept the lock, this would wait for the busy timeout
        second.connection().exec_driver_sql("PRAGMA busy_timeout = 200")
        write_labels(second, s, ids["bob"], [a], [1], expected_versions=[1])
        assert human(second, s) == {a: 1}


def test_box_reads_exactly_the_pillars_inside(session: Session, ids: dict) -> None:
    s = ids["survey"]
    rng = np.random.default_rng(0)
    xy = rng.uniform(-30, 30, size=(3000, 2))
    c = np.unique(cells([tuple(p) for p in xy]))
    write_labels(session, s, ids["anna"], c, np.arange(len(c)) % 4)
    session.add(
        PillarLabel(survey_id=s, cell_id=int(c[0]), label=2, source="model", confidence=0.4)
    )
    session.commit()
    box = (-10.0, -5.0, 12.0, 20.0)
    tile = labels_in_box(session, s, box)
    centres = STORE_GRID.cell_center(*STORE_GRID.decode(c))
    inside = (
        (centres[:, 0] >= box[0] - 0.2)
        & (centres[:, 0] < box[2] + 0.2)
        & (centres[:, 1] >= box[1] - 0.2)
        & (centres[:, 1] < box[3] + 0.2)
    )
    human_tile = tile.cell_id[tile.source == "human"]
    ix, iy = STORE_GRID.decode(human_tile)
    (ix0, iy0), (ix1, iy1) = STORE_GRID.cell_index(np.array([box[:2], box[2:]]))
    assert ((ix >= ix0) & (ix <= ix1) & (iy >= iy0) & (iy <= iy1)).all()
    expected = c[inside]
    ex, ey = STORE_GRID.decode(expected)
    expected = expected[(ex >= ix0) & (ex <= ix1) & (ey >= iy0) & (ey <= iy1)]
    assert sorted(human_tile.tolist()) == sorted(expected.tolist())
    assert len(labels_in_box(session, s, box, LabelSource.human).cell_id) == len(expected)
    served = json.loads(tile_json(session, s, box))
    assert served["count"] == len(tile.cell_id) >= len(expected)
    assert served["cell_id"] == tile.cell_id.tolist()
    assert served["source"] == tile.source.tolist()
    assert served["label"] == tile.label.tolist()
    ix, iy = STORE_GRID.decode(tile.cell_id)
    assert (served["ix"], served["iy"]) == (ix.tolist(), iy.tolist())
    assert served["confidence"].count(None) == len(expected)  # the human labels
    with pytest.raises(ConfigError, match="box"):
        box_cell_ranges(0, 0, -1, 1)


def test_uncertain_areas_rank_unreviewed_doubt(session: Session, ids: dict) -> None:
    s = ids["survey"]
    doubtful = cells([(1.1 + 0.2 * i, 1.1) for i in range(5)])
    sure = cells([(55.0, 55.0)])
    session.add_all(
        PillarLabel(survey_id=s, cell_id=int(c), label=3, source="model", confidence=0.5)
        for c in doubtful
    )
    session.add(
        PillarLabel(survey_id=s, cell_id=int(sure[0]), label=0, source="model", confidence=0.6)
    )
    session.commit()
    areas = uncertain_areas(session, s)
    assert [a.pillars for a in areas] == [5, 1]
    assert (areas[0].x, areas[0].y) == (5.0, 5.0)
    write_labels(session, s, ids["anna"], doubtful, [3] * 5)  # reviewed: leaves the queue
    assert [a.pillars for a in uncertain_areas(session, s)] == [1]
    assert label_counts(session, s) == {"human": [0, 0, 0, 5], "model": [1, 0, 0, 5]}
    assert human_labels_since(session, None) == 5
