"""Shared survey views follow the store through the label feed: human labels in full colour,
model pre-labels lighter by confidence, undo restores, writes from any session are seen; a
client's label write is checked against the label versions its view shows."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.core.errors import StaleWriteError
from app.core.sensors import SensorKind
from app.store.model_labels import store_model_labels
from app.store.model_versions import register_version
from app.store.models import Pipeline, Role, Survey
from app.store.pillar_labels import (
    NO_LABEL,
    STORE_GRID,
    current_human,
    undo,
    write_labels,
)
from app.store.users import create_user
from app.viewer.label_feed import LabelFeed, read_changes
from app.viewer.pillar_colors import PALETTE, UNLABELLED
from app.viewer.session import ViewerSession
from app.viewer.survey_view import SurveyViews
from app.viewer.tickets import Ticket


def open_view(engine: Engine, survey: Survey, tmp_path: Path):
    views = SurveyViews(engine, tmp_path / "cache", overview_points=10_000)
    return views, views.acquire(survey.id)


def box_cells(view) -> np.ndarray:
    """Store ids of the pillars holding the box's points (above 1 m over the street)."""
    m = view.map
    high = m.xyz[:, 2] - 0.02 * m.xyz[:, 0] > 1.0
    return m.cells[np.unique(m.cell[high])]


def user_id(engine: Engine, name: str) -> int:
    with Session(engine) as session:
        return create_user(session, name, "password-123", Role.annotator).id


def model_version(engine: Engine, tmp_path: Path) -> int:
    with Session(engine) as session:
        version = register_version(
            session, Pipeline.phantom, "test", tmp_path / "m.pt", {}, {}, None,
            promote=False, sensor_kind=SensorKind.PROFILE,
        )  # fmt: skip
        session.commit()
        return version.id


def test_view_starts_unlabelled_and_follows_writes(
    engine: Engine, ply_survey: Survey, tmp_path: Path
) -> None:
    views, view = open_view(engine, ply_survey, tmp_path)
    assert (view.rgb == PALETTE[UNLABELLED]).all()
    heard: list[np.ndarray] = []
    view.subscribe(heard.append)
    feed = LabelFeed(engine, lambda changes: [view.refresh_human(c.human_cells) for c in changes])
    feed.start()
    feed.stop()  # poll by hand below
    alice = user_id(engine, "alice")
    cells = box_cells(view)
    with Session(engine) as session:
        write_labels(session, ply_survey.id, alice, cells, np.full(len(cells), 1))
    feed.poll()
    k, found = view.map.cell_index(cells)
    assert found.all() and len(heard) == 1
    np.testing.assert_array_equal(np.sort(heard[0]), np.sort(k))
    assert (view.human[k] == 1).all()
    assert (view.rgb[k] == PALETTE[1]).all()  # human: full colour
    box_points = np.flatnonzero(np.isin(view.map.cell, k))
    assert (view.point_colors(box_points) == PALETTE[1]).all()

    with Session(engine) as session:
        undo(session, ply_survey.id, alice)
    feed.poll()
    assert (view.human[k] == -1).all() and (view.rgb[k] == PALETTE[UNLABELLED]).all()
    assert len(heard) == 2
    feed.poll()  # nothing new: no announcement
    assert len(heard) == 2
    views.release(view)


def test_model_prelabels_are_lighter_the_less_sure(
    engine: Engine, ply_survey: Survey, tmp_path: Path
) -> None:
    views, view = open_view(engine, ply_survey, tmp_path)
    cells = view.map.cells[:3]
    store_model_labels(
        engine,
        ply_survey.id,
        cells,
        np.array([0, 0, 3]),
        np.array([0.99, 0.3, 0.6]),
        model_version(engine, tmp_path),
        None,
        job_id=0,
    )
    with Session(engine) as session:
        _, changes = read_changes(session, 0)
    assert [(c.survey_id, c.model_replaced) for c in changes] == [(ply_survey.id, True)]
    view.load_all()
    sure, unsure, phantom = view.rgb[:3].astype(int)
    ground = PALETTE[0].astype(int)
    assert (sure >= ground).all() and (unsure >= sure).all() and (unsure > sure).any()
    assert (sure < 255).any()  # still a colour, not white
    assert phantom[0] > phantom[1]  # a light magenta
    # a human label over a model one shows the human label in full colour
    bob = user_id(engine, "bob")
    with Session(engine) as session:
        write_labels(session, ply_survey.id, bob, cells[:1], [2])
    view.refresh_human(cells[:1])
    assert (view.rgb[0] == PALETTE[2]).all()
    with Session(engine) as session:
        write_labels(session, ply_survey.id, bob, cells[:1], [NO_LABEL])
    view.refresh_human(cells[:1])
    assert (view.rgb[0] == sure).all()  # erased: the model's label shows again
    views.release(view)


def test_views_are_shared_and_dropped_with_the_last_client(
    engine: Engine, ply_survey: Survey, tmp_path: Path
) -> None:
    views, first = open_view(engine, ply_survey, tmp_path)
    second = views.acquire(ply_survey.id)
    assert second is first and views.open_ids() == [ply_survey.id]
    views.release(first)
    assert views.get(ply_survey.id) is first
    views.release(second)
    assert views.get(ply_survey.id) is None


class ViewerStandIn:
    """What a ViewerSession's label writes use of the viewer server: its engine and the
    wake-up of the label feed (not polled here: the view must not rely on it)."""

    def __init__(self, engine: Engine):
        self.engine = engine
        self.wakes = 0

    def labels_written(self) -> None:
        self.wakes += 1


def test_a_client_never_overwrites_a_label_it_has_not_seen(
    engine: Engine, ply_survey: Survey, tmp_path: Path
) -> None:
    views, view = open_view(engine, ply_survey, tmp_path)
    viewer = ViewerStandIn(engine)
    ticket = Ticket(user_id(engine, "alice"), "alice", ply_survey.id)
    alice = ViewerSession(viewer, SimpleNamespace(client_id=1), ticket)
    alice.view = view
    cells = box_cells(view)
    first = alice.write_pillar_labels(cells, np.full(len(cells), 2))
    k, _ = view.map.cell_index(cells)
    # her own write is in the view at once, with its versions: her next action is not refused
    assert (view.human[k] == 2).all() and view.human_versions(cells) == first.versions.tolist()
    alice.write_pillar_labels(cells[:5], np.full(5, 1))

    # bob labels some of the same pillars; the label feed has not told her view yet
    bob = user_id(engine, "bob")
    with Session(engine) as session:
        bobs = write_labels(session, ply_survey.id, bob, cells[3:8], np.full(5, 3))
    with pytest.raises(StaleWriteError) as refused:
        alice.write_pillar_labels(cells[:10], np.full(10, 0))
    assert sorted(c["cell_id"] for c in refused.value.current) == sorted(cells[3:8].tolist())
    with Session(engine) as session:
        stored = current_human(session, ply_survey.id, cells[:10])
    assert [stored[c][0] for c in cells[:10].tolist()] == [1, 1, 1, 3, 3, 3, 3, 3, 2, 2]
    # nothing written, and her view now shows bob's labels: a second try is her own choice;
    # the labels her refused write showed before the store answered are taken back
    assert view.human[k[:10]].tolist() == [1, 1, 1, 3, 3, 3, 3, 3, 2, 2]
    assert view.human_versions(cells[3:8]) == bobs.versions.tolist()
    alice.write_pillar_labels(cells[:10], np.full(10, 0))
    with Session(engine) as session:
        stored = current_human(session, ply_survey.id, cells[:10])
    assert {stored[c][0] for c in cells[:10].tolist()} == {0}

    # undo and redo keep the view's versions current too
    alice.undo_pillars()
    assert view.human[k[:10]].tolist() == [1, 1, 1, 3, 3, 3, 3, 3, 2, 2]
    alice.write_pillar_labels(cells[:2], np.full(2, 3))
    # a pillar without points is not shown, so not checked
    empty = STORE_GRID.point_cell_ids(view.map.origin[:2] + np.array([[-50.0, -50.0]]))
    assert view.human_versions(empty) == [None]
    alice.write_pillar_labels(empty, [1])
    assert viewer.wakes == 6
    views.release(view)


def test_an_erased_label_shows_as_none_with_the_version_of_its_erase(
    engine: Engine, ply_survey: Survey, tmp_path: Path
) -> None:
    """A view loaded after an erase shows no label there, but keeps the erase's version: its
    client's write over the pillar passes (version 0 would be refused: versions only grow)."""
    views, view = open_view(engine, ply_survey, tmp_path)
    cells = box_cells(view)[:4]
    bob = user_id(engine, "bob")
    with Session(engine) as session:
        write_labels(session, ply_survey.id, bob, cells, np.full(4, 2))
        write_labels(session, ply_survey.id, bob, cells[:2], np.full(2, NO_LABEL))
    view.load_all()
    k, _ = view.map.cell_index(cells)
    assert view.human[k].tolist() == [-1, -1, 2, 2]
    assert (view.rgb[k[:2]] == PALETTE[UNLABELLED]).all()
    assert view.human_versions(cells) == [2, 2, 1, 1]
    ticket = Ticket(user_id(engine, "alice"), "alice", ply_survey.id)
    alice = ViewerSession(ViewerStandIn(engine), SimpleNamespace(client_id=1), ticket)
    alice.view = view
    assert alice.write_pillar_labels(cells, np.full(4, 1)).versions.tolist() == [3, 3, 2, 2]
    views.release(view)


def test_a_write_is_shown_before_the_store_has_it_and_told_to_the_others_after(
    engine: Engine, ply_survey: Survey, tmp_path: Path
) -> None:
    """The writer's colours go out before SQLite's write (a large batch's half second): the
    view shows the labels with the stored versions, tells nobody, then takes the written
    versions and tells every listener but the writer; a refused write is taken back."""
    views, view = open_view(engine, ply_survey, tmp_path)
    heard: list[np.ndarray] = []
    view.subscribe(heard.append)

    def writer(changed: np.ndarray) -> None:
        raise AssertionError("the writer was told of its own write")

    view.subscribe(writer)
    cells = box_cells(view)
    labels = np.full(len(cells), 1)
    k, _ = view.map.cell_index(cells)
    shown = view.show_labels(cells, labels)
    assert sorted(shown.tolist()) == sorted(k.tolist()) and (view.human[k] == 1).all()
    assert heard == [] and view.human_versions(cells) == [0] * len(cells)
    with Session(engine) as session:
        result = write_labels(session, ply_survey.id, user_id(engine, "carol"), cells, labels)
    changed = view.take_written(result.cell_ids, labels, result.versions, shown, writer)
    assert len(changed) == 0 and len(heard) == 1
    assert sorted(heard[0].tolist()) == sorted(shown.tolist())
    assert view.human_versions(cells) == result.versions.tolist()
    # shown, then refused: the store's labels come back (and are told)
    view.show_labels(cells[:3], np.full(3, 3))
    view.unsubscribe(writer)
    view.refresh_human(cells[:3])
    assert (view.human[k[:3]] == 1).all() and len(heard) == 2
    views.release(view)
