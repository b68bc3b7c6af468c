"""Reviewers' corrections of clutter instances on a real `run:clutter` of a small simulated
street (the real ESPNetv2 weights): points taken out of an instance and a missed object added,
through the review service and the store (versions, 409 on stale, refused input, audit), then
`clutter:recompute` and the SemanticKITTI export apply them."""

from __future__ import annotations

import zipfile
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import laspy
import numpy as np
import pytest
from sqlmodel import Session, select

from app.core.errors import ConfigError, ConflictError, NotFoundError, StaleWriteError
from app.core.labels import CLUTTER_CLASS_SEMANTIC
from app.io.semantickitti import read_label_file
from app.jobs.clutter_tasks import recompute_clutter
from app.reports.exports import slug
from app.reports.semantickitti_labels import write_semantickitti_zip
from app.review import clutter_corrections
from app.store.clutter_corrections import correction_counts, survey_corrections
from app.store.clutter_review import get_instance, list_instances, replace_instances
from app.store.models import (
    AuditEvent,
    ClutterCorrection,
    Decision,
    Job,
    JobStatus,
    Role,
    Survey,
)
from app.store.users import create_user
from tests.jobs.conftest import clutter_street, job_context
from tests.pipelines.clutter.conftest import weights_dir  # noqa: F401  (the fixture)


@pytest.fixture(scope="module")
def ran(tmp_path_factory: pytest.TempPathFactory, weights_dir: Path) -> Iterator[dict]:  # noqa: F811
    """A 7-frame simulated street registered in a fresh store and run through `run:clutter`."""
    street = clutter_street(tmp_path_factory.mktemp("clutter-corrections"), weights_dir)
    with Session(street["context"].engine) as session:
        street["user"] = create_user(session, "corrector", "password-123", Role.reviewer).id
    yield street
    street["context"].engine.dispose()


def map_points(path: str) -> int:
    return len(laspy.read(path).points)


def test_corrections_are_versioned_checked_and_applied_by_recompute(
    ran: dict, tmp_path: Path
) -> None:
    context, survey, result = ran["context"], ran["survey"], ran["result"]
    engine, settings, sid = context.engine, ran["settings"], context.survey_id
    user = ran["user"]
    with Session(engine) as session:
        _, states = list_instances(session, sid, limit=1000)
    member = {
        f.frame_id: np.load(context.workdir / "instances" / f"{f.frame_id}.npz")
        for f in survey.frames
    }
    # the instance with the most points the pipeline removes: take half of them out of it
    removes = {
        s.id: int(
            (
                (member[s.frame_id]["instance"] == s.instance_index) & member[s.frame_id]["removed"]
            ).sum()
        )
        for s in states
    }
    target = max(states, key=lambda s: removes[s.id])
    owner = member[target.frame_id]["instance"]
    flags = member[target.frame_id]["removed"].astype(bool)
    mine = np.flatnonzero(owner == target.instance_index)
    taken = mine[: len(mine) // 2]
    other = np.flatnonzero((owner >= 0) & (owner != target.instance_index))[:1]
    with Session(engine) as session:
        done = clutter_corrections.remove_points(
            session, sid, target.id, target.version, [*taken.tolist(), *other.tolist()], user
        )
    assert done.points == len(taken)  # the other instance's point is left to it
    assert done.state.version == target.version + 1
    assert done.state.point_count == target.point_count - len(taken)
    assert done.state.decision == Decision.pending

    # stale version: 409 with the instance as it is now, nothing written
    with Session(engine) as session, pytest.raises(StaleWriteError) as stale:
        clutter_corrections.remove_points(
            session, sid, target.id, target.version, mine[-3:].tolist(), user
        )
    assert stale.value.current[0]["version"] == target.version + 1
    # bad input: no point of the instance, a point outside the frame, an unknown instance
    with Session(engine) as session:
        with pytest.raises(ConfigError, match="none of the"):
            clutter_corrections.remove_points(
                session, sid, target.id, done.state.version, taken[:5].tolist(), user
            )
        with pytest.raises(ConfigError, match=r"points\[0\]"):
            clutter_corrections.remove_points(
                session, sid, target.id, done.state.version, [len(owner) + 5], user
            )
        with pytest.raises(NotFoundError):
            clutter_corrections.remove_points(session, sid, 10**9, 1, [0], user)
        assert len(session.exec(select(ClutterCorrection)).all()) == 1

    # a missed object: free points of another frame (the corrected ones of this frame too)
    frame_b = next(f.frame_id for f in survey.frames if f.frame_id != target.frame_id)
    owner_b = member[frame_b]["instance"]
    free_b = np.flatnonzero(owner_b < 0)[:40]
    owned_b = np.flatnonzero(owner_b >= 0)[:3]
    with Session(engine) as session:
        added = clutter_corrections.add_object(
            session, sid, frame_b, "person", [*free_b.tolist(), *owned_b.tolist()], user
        )
        with pytest.raises(ConfigError, match="class_name"):
            clutter_corrections.add_object(session, sid, frame_b, "tree", free_b.tolist(), user)
        with pytest.raises(ConfigError, match="already belong"):
            clutter_corrections.add_object(session, sid, frame_b, "car", free_b.tolist(), user)
        with pytest.raises(NotFoundError):
            clutter_corrections.add_object(session, sid, "no-such-frame", "car", [0], user)
    state = added.state
    assert added.points == len(free_b) and state.point_count == len(free_b)
    assert state.decision == Decision.approved and state.version == 1 and state.user_id == user
    assert state.mask_path is None and state.instance_index > int(owner_b.max())
    with Session(engine) as session:
        assert correction_counts(session, sid) == {"remove": 1, "add": 1}
        assert set(survey_corrections(session, sid)) == {target.frame_id, frame_b}
        actions = session.exec(select(AuditEvent.action).where(AuditEvent.user_id == user)).all()
    assert sorted(actions) == ["clutter.add_object", "clutter.remove_points"]

    # recompute: the taken points the pipeline removed are kept, the added object is removed
    out = recompute_clutter(job_context(settings, engine, 2, sid), {})
    before = map_points(result["files"]["cleaned"])
    expected = before + int(flags[taken].sum()) - len(free_b)
    assert int(flags[taken].sum()) > 0
    assert map_points(out["files"]["cleaned"]) == expected
    assert map_points(out["files"]["removed"]) == result["counts"]["points"] - expected
    assert out["counts"]["corrections"] == {"remove": 1, "add": 1}
    labels_a = np.load(Path(out["files"]["labels"]) / f"{target.frame_id}.npy")
    labels_b = np.load(Path(out["files"]["labels"]) / f"{frame_b}.npy")
    assert not labels_a[taken].any() and labels_b[free_b].all()

    # the SemanticKITTI export applies them too: the added object's points are people
    now = datetime.now(UTC)
    with Session(engine) as session:
        session.add(
            Job(survey_id=sid, kind="run:clutter", status=JobStatus.succeeded,
                result=result, started_at=now, finished_at=now)
        )  # fmt: skip
        session.commit()
        record = session.get(Survey, sid)
        write_semantickitti_zip(session, settings, record, tmp_path / "labels.zip")
    with zipfile.ZipFile(tmp_path / "labels.zip") as zf:
        zf.extractall(tmp_path)
    frame = next(f for f in survey.frames if f.frame_id == frame_b)
    read = read_label_file(
        tmp_path / "sequences" / slug(record.name) / "labels" / f"{frame_b}.label",
        frame.point_count,
    )
    assert (read["semantic"][free_b] == int(CLUTTER_CLASS_SEMANTIC["person"])).all()

    # a new run replaces the instances: their corrections go with them, and a membership
    # read before the new run is refused
    with Session(engine) as session:
        stale_membership = clutter_corrections.run_membership(session, sid, frame_b)
        mask = tmp_path / "run2" / "instances" / frame_b / "0.png"  # another run's instance
        replace_instances(
            session, sid,
            [{"frame_id": frame_b, "instance_index": 0, "class_name": "car", "point_count": 1,
              "mask_path": str(mask), "bbox": None, "moving": None, "track_id": None}],
            None,
        )  # fmt: skip
        assert session.exec(select(ClutterCorrection)).all() == []
        with pytest.raises(ConflictError):
            clutter_corrections.add_object(
                session, sid, frame_b, "car", free_b.tolist(), user, stale_membership
            )
        with pytest.raises(NotFoundError):
            get_instance(session, sid, state.id)
