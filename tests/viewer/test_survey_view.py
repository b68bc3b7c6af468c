"""Shared survey views follow the store through the label feed: human labels in full colour,
model pre-labels lighter by confidence, undo restores, writes from any session are seen."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.jobs.phantom_tasks import store_model_labels
from app.store.model_versions import register_version
from app.store.models import Pipeline, Role, Survey
from app.store.pillar_labels import NO_LABEL, undo, write_labels
from app.store.users import create_user
from app.viewer.label_feed import LabelFeed, read_changes
from app.viewer.pillar_colors import PALETTE, UNLABELLED
from app.viewer.survey_view import SurveyViews


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
            session, Pipeline.phantom, "test", tmp_path / "m.pt", {}, {}, None, promote=False
        )
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
