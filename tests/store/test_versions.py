"""Versions only grow: the one conflict check, erases that keep their version (tombstones),
undo / redo checked by version, and ids that replaced review rows never get back."""

from __future__ import annotations

import json

import numpy as np
import pytest
from sqlmodel import Session, select

from app.core.errors import NotFoundError, StaleWriteError
from app.store.clutter_review import DecisionWrite, decide, list_instances, replace_instances
from app.store.guardrail_review import (
    SliceLabelEdit,
    decide_model,
    list_models,
    list_slices,
    put_slice_labels,
)
from app.store.guardrail_runs import ModelRecord, SliceRows, replace_guardrail_run
from app.store.models import (
    ClutterInstance,
    Decision,
    GuardrailKind,
    LabelSource,
    ModelStatus,
    PillarEdit,
    PillarLabel,
    PillarTombstone,
    Role,
    Survey,
    User,
    utcnow,
)
from app.store.pillar_labels import NO_LABEL, STORE_GRID, human_columns, redo, undo, write_labels
from app.store.pillar_reads import (
    human_labels_since,
    label_counts,
    labels_in_box,
    tile_json,
    uncertain_areas,
)
from app.store.versions import NOT_CHECKED, check_versions, fresh_ids


@pytest.fixture
def ids(session: Session) -> dict[str, int]:
    survey = Survey(name="s", format="sim", source_path="/s")
    users = [User(username=n, hashed_password="x", role=Role.reviewer) for n in ("ann", "rev")]
    users.append(User(username="ann2", hashed_password="x", role=Role.reviewer))
    session.add_all([survey, *users])
    session.commit()
    return {"survey": survey.id, **{u.username: u.id for u in users}}


def cell(x: float, y: float) -> int:
    ix, iy = STORE_GRID.cell_index(np.array([[x, y]]))[0]
    return int(STORE_GRID.cell_id(ix, iy))


def human(session: Session, survey: int) -> dict[int, int]:
    rows = session.exec(
        select(PillarLabel).where(
            PillarLabel.survey_id == survey, PillarLabel.source == LabelSource.human
        )
    ).all()
    return {r.cell_id: r.label for r in rows}


# --- the check ------------------------------------------------------------------------------


def test_check_versions_names_the_field_the_record_and_both_versions() -> None:
    seen = {}

    def states(keys: np.ndarray) -> list[int]:
        seen["keys"] = keys.tolist()
        return ["now"] * len(keys)

    check_versions([7, 8], [3, NOT_CHECKED], [3, 5], field="slices", noun="slice", states=states)
    with pytest.raises(StaleWriteError) as caught:
        check_versions([7, 8, 9], [3, 4, 1], [3, 5, 2], field="slices", noun="slice", states=states)
    message = caught.value.message
    assert message.startswith("slices: 2 slice(s) changed by someone else: slice 8 ")
    assert "is at version 5, not 4 (and 1 more); reload and retry" in message
    assert seen["keys"] == [8, 9] and caught.value.current == ["now", "now"]


def test_fresh_ids_are_never_handed_out_twice(session: Session, ids: dict) -> None:
    table = ClutterInstance.__table__
    assert fresh_ids(session, table, 3) == 1  # an empty table
    assert fresh_ids(session, table, 2) == 4  # nothing inserted, yet never the same again
    session.commit()
    row = {"frame_id": "f", "instance_index": 0, "class_name": "car", "created_at": utcnow()}
    session.connection().execute(table.insert(), [{**row, "id": 50, "survey_id": ids["survey"]}])
    assert fresh_ids(session, table, 1) == 51  # above live rows written some other way
    session.connection().execute(table.delete())
    assert fresh_ids(session, table, 1) == 52  # and above deleted ones


# --- pillar labels: erases keep their version ------------------------------------------------


def test_a_stale_write_after_an_erase_is_refused(session: Session, ids: dict) -> None:
    """The issue's sequence (ABA): ann labels, rev reads version 1, ann2 erases, ann labels
    again; rev's write at version 1 must be refused, not replace ann's label unseen."""
    s, a = ids["survey"], cell(1.0, 1.0)
    assert write_labels(session, s, ids["ann"], [a], [1], [0]).versions.tolist() == [1]
    rev_saw = 1
    assert write_labels(session, s, ids["ann2"], [a], [NO_LABEL], [1]).versions.tolist() == [2]
    with pytest.raises(StaleWriteError) as never_saw_the_erase:
        write_labels(session, s, ids["ann"], [a], [2], [0])
    assert never_saw_the_erase.value.current[0]["label"] is None
    assert never_saw_the_erase.value.current[0]["version"] == 2
    assert write_labels(session, s, ids["ann"], [a], [2], [2]).versions.tolist() == [3]
    with pytest.raises(StaleWriteError, match="pillar .* is at version 3, not 1") as caught:
        write_labels(session, s, ids["rev"], [a], [3], [rev_saw])
    assert caught.value.current[0]["label"] == 2
    assert human(session, s) == {a: 2}
    assert session.exec(select(PillarTombstone)).all() == []  # the label replaced it


def test_tombstones_are_no_labels_to_readers(session: Session, ids: dict) -> None:
    s = ids["survey"]
    a, b = cell(2.0, 2.0), cell(2.5, 2.0)
    session.add(PillarLabel(survey_id=s, cell_id=b, label=3, source="model", confidence=0.2))
    session.commit()
    write_labels(session, s, ids["ann"], [a, b], [1, 2])
    before = human_labels_since(session, None)
    write_labels(session, s, ids["ann"], [a, b], [NO_LABEL, NO_LABEL])
    assert human(session, s) == {}
    assert label_counts(session, s)["human"] == [0, 0, 0, 0]
    assert human_labels_since(session, None) == before - 2
    box = (1.0, 1.0, 3.0, 3.0)
    assert len(labels_in_box(session, s, box, LabelSource.human).cell_id) == 0
    tile = json.loads(tile_json(session, s, box))
    assert tile["source"] == ["model"] and tile["count"] == 1
    assert sorted(zip(tile["erased_cell_id"], tile["erased_version"], strict=True)) == sorted(
        [(a, 2), (b, 2)]
    )
    model_only = json.loads(tile_json(session, s, box, LabelSource.model))
    assert model_only["erased_cell_id"] == []
    assert uncertain_areas(session, s)[0].cell_ids == [b]  # unreviewed again
    labels, versions = human_columns(session, s, np.array([a, b, cell(9.0, 9.0)]))
    assert labels.tolist() == [NO_LABEL] * 3 and versions.tolist() == [2, 2, 0]
    # erasing again is a new version too; the survey's deletion takes the tombstones along
    assert write_labels(session, s, ids["ann"], [a], [NO_LABEL], [2]).versions.tolist() == [3]
    session.delete(session.get(Survey, s))
    session.commit()
    assert session.exec(select(PillarTombstone)).all() == []


# --- pillar labels: undo / redo by version ----------------------------------------------------


def test_undo_refuses_a_label_that_came_back_from_someone_else(session: Session, ids: dict) -> None:
    """ann labels 2; rev relabels 1, ann2 relabels 2: the label is ann's again but not her
    write. Her undo would erase ann2's label unseen (the old check compared labels only)."""
    s, a = ids["survey"], cell(3.0, 3.0)
    write_labels(session, s, ids["ann"], [a], [2])
    write_labels(session, s, ids["rev"], [a], [1], [1])
    write_labels(session, s, ids["ann2"], [a], [2], [2])
    with pytest.raises(StaleWriteError, match="cannot undo: 1 of its pillar labels"):
        undo(session, s, ids["ann"])
    assert human(session, s) == {a: 2}


def test_undo_and_redo_of_an_erase_are_new_versions(session: Session, ids: dict) -> None:
    s, a = ids["survey"], cell(4.0, 4.0)
    write_labels(session, s, ids["ann"], [a], [1])
    write_labels(session, s, ids["ann"], [a], [NO_LABEL], [1])
    assert undo(session, s, ids["ann"]).versions.tolist() == [3]  # the label is back
    assert human(session, s) == {a: 1}
    with pytest.raises(StaleWriteError):  # version 1 saw this label once, but not now
        write_labels(session, s, ids["rev"], [a], [0], [1])
    assert redo(session, s, ids["ann"]).versions.tolist() == [4]  # erased again
    assert human_columns(session, s, np.array([a]))[1].tolist() == [4]
    assert undo(session, s, ids["ann"]).versions.tolist() == [5]
    assert undo(session, s, ids["ann"]).versions.tolist() == [6]  # the first label goes too
    assert human(session, s) == {}


def test_an_undo_hands_the_version_on_to_the_edits_it_restores(session: Session, ids: dict) -> None:
    s, a = ids["survey"], cell(5.0, 5.0)
    write_labels(session, s, ids["ann"], [a], [3])
    write_labels(session, s, ids["rev"], [a], [0], [1])
    with pytest.raises(StaleWriteError):
        undo(session, s, ids["ann"])  # rev's label is there
    undo(session, s, ids["rev"])  # ann's label is back, at version 3
    assert human(session, s) == {a: 3}
    assert undo(session, s, ids["ann"]).versions.tolist() == [4]  # hers to undo again
    with pytest.raises(StaleWriteError):
        redo(session, s, ids["rev"])  # rev's undo is no longer what is there
    assert redo(session, s, ids["ann"]).versions.tolist() == [5]


def test_edits_from_before_versions_undo_by_label(session: Session, ids: dict) -> None:
    s, a, b = ids["survey"], cell(6.0, 6.0), cell(7.0, 7.0)
    write_labels(session, s, ids["ann"], [a], [3])
    write_labels(session, s, ids["rev"], [b], [1])
    legacy = "UPDATE pillar_edit SET version = NULL, version_before = NULL"  # as schema v3 left
    session.connection().exec_driver_sql(legacy)
    session.commit()
    assert undo(session, s, ids["ann"]).versions.tolist() == [2]  # label unchanged: allowed
    write_labels(session, s, ids["ann2"], [b], [2], [1])
    with pytest.raises(StaleWriteError, match="pillar .* no longer as this edit left it"):
        undo(session, s, ids["rev"])
    assert redo(session, s, ids["ann"]).versions.tolist() == [3]  # a version from now on
    assert session.exec(select(PillarEdit.version).where(PillarEdit.cell_id == a)).all() == [3]


# --- review rows replaced by a run -------------------------------------------------------------


def _instances(n: int) -> list[dict]:
    return [
        {"frame_id": "f0", "instance_index": k, "class_name": "car", "point_count": 10}
        for k in range(n)
    ]


def test_a_clutter_rerun_never_gives_an_old_instance_id_to_a_new_instance(
    session: Session, ids: dict
) -> None:
    s = ids["survey"]
    replace_instances(session, s, _instances(3), None)
    _, held = list_instances(session, s)
    replace_instances(session, s, [], None)  # a run that found nothing
    replace_instances(session, s, _instances(3), None)
    _, now = list_instances(session, s)
    assert not {i.id for i in held} & {i.id for i in now}
    with pytest.raises(NotFoundError):  # not an approval of a new instance at version 1
        decide(session, s, [DecisionWrite(held[0].id, 1, Decision.approved)], ids["rev"])
    assert all(i.decision == Decision.pending for i in list_instances(session, s)[1])
    written = decide(session, s, [DecisionWrite(now[0].id, 1, Decision.approved)], ids["rev"])
    assert written[0].version == 2
    with pytest.raises(StaleWriteError, match="decisions: 1 clutter instance"):
        decide(session, s, [DecisionWrite(now[0].id, 1, Decision.pending)], ids["rev"])


def _slices(n: int) -> SliceRows:
    k = np.arange(n)
    return SliceRows(
        component=np.zeros(n, np.int64),
        slice_index=k,
        station=0.5 * k,
        predicted=np.ones(n, np.int64),
        probability=np.full(n, 0.6),
        corrected=np.ones(n, np.int64),
    )


def _run(session: Session, survey: int, slices: int, models: int) -> None:
    record = ModelRecord(GuardrailKind.beam, "m.ply", {}, 1, None, [(0, 0)])
    replace_guardrail_run(
        session, survey, _slices(slices), [record] * models, stage_path="stage.npz",
        config={}, job_id=None, user_id=None,
    )  # fmt: skip


def test_a_guardrail_rerun_never_gives_an_old_id_to_a_new_slice_or_model(
    session: Session, ids: dict
) -> None:
    s = ids["survey"]
    rev = session.get(User, ids["rev"])
    _run(session, s, 3, 1)
    _, held = list_slices(session, s)
    held_slice, held_model = held[0].id, list_models(session, s)[0].id
    _run(session, s, 0, 0)  # a run that found nothing
    _run(session, s, 3, 1)
    _, now = list_slices(session, s)
    assert held_slice not in {r.id for r in now}
    assert held_model not in {m.id for m in list_models(session, s)}
    with pytest.raises(NotFoundError):
        put_slice_labels(session, s, [SliceLabelEdit(held_slice, 1, 0)], rev)
    with pytest.raises(NotFoundError):
        decide_model(session, s, held_model, 1, ModelStatus.approved, rev)
    new_slice, new_model = now[0].id, list_models(session, s)[0].id
    assert put_slice_labels(session, s, [SliceLabelEdit(new_slice, 1, 0)], rev)[0].version == 2
    with pytest.raises(StaleWriteError, match="slices: 1 slice"):
        put_slice_labels(session, s, [SliceLabelEdit(new_slice, 1, 1)], rev)
    decide_model(session, s, new_model, 1, ModelStatus.approved, rev)
    with pytest.raises(StaleWriteError, match="version: 1 guardrail model"):
        decide_model(session, s, new_model, 1, ModelStatus.rejected, rev)
