"""Clutter jobs run directly: `run:clutter` ingests its instances for review with their point
membership, `clutter:recompute` rebuilds the maps from the decisions (a small simulated street,
the real ESPNetv2 weights)."""

from __future__ import annotations

import threading
import zipfile
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import cv2
import laspy
import numpy as np
import pytest
from sqlmodel import Session, select

from app.core.errors import ConfigError, StaleWriteError
from app.core.labels import MOVING_OFFSET
from app.core.settings import Settings
from app.io.semantickitti import read_label_file
from app.jobs.clutter_tasks import recompute_clutter, run_clutter_task
from app.reports.exports import slug
from app.reports.semantickitti_labels import write_semantickitti_zip
from app.store import clutter_review
from app.store.clutter_review import (
    DecisionWrite,
    decide,
    list_instances,
    replace_instances,
    review_decisions,
)
from app.store.db import init_db, make_engine
from app.store.models import (
    AuditEvent,
    ClutterDecision,
    ClutterInstance,
    Decision,
    Job,
    JobStatus,
    Survey,
)
from tests.jobs.conftest import clutter_street, job_context
from tests.pipelines.clutter.conftest import weights_dir  # noqa: F401  (the fixture)


@pytest.fixture(scope="module")
def ran(tmp_path_factory: pytest.TempPathFactory, weights_dir: Path) -> Iterator[dict]:  # noqa: F811
    """A 7-frame simulated street registered in a fresh store and run through `run:clutter`."""
    street = clutter_street(tmp_path_factory.mktemp("clutter-jobs"), weights_dir)
    yield street
    street["context"].engine.dispose()


def test_run_ingests_every_instance_pending(ran: dict) -> None:
    context, result = ran["context"], ran["result"]
    for name in ("cleaned", "removed", "report", "labels", "instances"):
        assert Path(result["files"][name]).is_absolute() and Path(result["files"][name]).exists()
    with Session(context.engine) as session:
        total, states = list_instances(session, context.survey_id, limit=1000)
    assert total == result["counts"]["instances"] == len(states) > 0
    assert {s.decision for s in states} == {Decision.pending} and {s.version for s in states} == {1}
    classes = {s.class_name for s in states}
    assert classes & {"person", "car", "truck", "bus", "train", "bicycle", "motorcycle", "rider"}
    for s in states[:: max(len(states) // 20, 1)]:  # mask images: readable PNGs in the run folder
        image = cv2.imread(s.mask_path)
        assert image is not None and image.ndim == 3
        assert Path(s.mask_path).is_relative_to(context.workdir.resolve())
    in_image = [s for s in states if s.bbox is not None]
    assert in_image and all(s.bbox[0] <= s.bbox[2] and s.bbox[1] <= s.bbox[3] for s in in_image)
    assert any(s.track_id is not None for s in states)


def test_membership_matches_the_labels(ran: dict) -> None:
    """Per frame: the npz's removed flags are labels/*.npy, every removed point belongs to an
    instance, and the store's instances are exactly the npz's, with their point counts."""
    context, survey = ran["context"], ran["survey"]
    with Session(context.engine) as session:
        _, states = list_instances(session, context.survey_id, limit=1000)
    by_frame: dict[str, dict[int, int]] = {}
    for s in states:
        by_frame.setdefault(s.frame_id, {})[s.instance_index] = s.point_count
    for frame in survey.frames:
        labels = np.load(context.workdir / "labels" / f"{frame.frame_id}.npy")
        member = np.load(context.workdir / "instances" / f"{frame.frame_id}.npz")
        owner, removed = member["instance"], member["removed"]
        assert len(owner) == len(labels) == len(frame.points())
        assert np.array_equal(removed, labels.astype(bool))
        assert (owner[removed] >= 0).all()
        sizes = np.bincount(owner[owner >= 0], minlength=int(owner.max(initial=-1)) + 1)
        assert by_frame.get(frame.frame_id, {}) == {i: int(n) for i, n in enumerate(sizes.tolist())}


def map_points(path: str) -> int:
    return len(laspy.read(path).points)


def test_recompute_applies_approvals_and_rejections(ran: dict) -> None:
    context, survey, result = ran["context"], ran["survey"], ran["result"]
    engine, settings = context.engine, ran["settings"]
    with Session(engine) as session:
        _, states = list_instances(session, context.survey_id, limit=1000)
    members = {
        f.frame_id: np.load(context.workdir / "instances" / f"{f.frame_id}.npz")
        for f in survey.frames
    }

    def split(s) -> tuple[int, int]:
        """(points the pipeline removed, points it kept) of an instance."""
        m = members[s.frame_id]
        mine = m["instance"] == s.instance_index
        return int((mine & m["removed"]).sum()), int((mine & ~m["removed"]).sum())

    # approve one with points the pipeline kept (if any), reject one it removed entirely
    partly_kept = [s for s in states if split(s)[1] > 0]
    approve = max(partly_kept or states, key=lambda s: split(s)[1])
    reject = max((s for s in states if s.id != approve.id), key=lambda s: split(s)[0])
    with Session(engine) as session:
        decide(
            session,
            context.survey_id,
            [
                DecisionWrite(approve.id, 1, Decision.approved),
                DecisionWrite(reject.id, 1, Decision.rejected),
            ],
            None,
        )
    assert split(approve)[1] > 0 and split(reject)[0] > 0  # both decisions change the map
    out = recompute_clutter(job_context(settings, engine, 2, context.survey_id), {})
    cleaned_before = map_points(result["files"]["cleaned"])
    expected = cleaned_before - split(approve)[1] + split(reject)[0]
    assert map_points(out["files"]["cleaned"]) == expected
    total = result["counts"]["points"]
    assert map_points(out["files"]["removed"]) == total - expected
    assert out["counts"]["map_points"] == expected and out["counts"]["decisions"]["approved"] == 1
    frame_labels = np.load(Path(out["files"]["labels"]) / f"{reject.frame_id}.npy")
    rejected = members[reject.frame_id]["instance"] == reject.instance_index
    assert not frame_labels[rejected].any()  # the rejected instance's points stay
    with Session(engine) as session:  # both decisions are audited
        actions = session.exec(select(AuditEvent.action)).all()
    assert {"clutter.approve", "clutter.reject", "clutter.ingest"} <= set(actions)

    # all pending again: the maps are the pipeline's own
    with Session(engine) as session:
        decide(
            session,
            context.survey_id,
            [
                DecisionWrite(approve.id, 2, Decision.pending),
                DecisionWrite(reject.id, 2, Decision.pending),
            ],
            None,
        )
    again = recompute_clutter(job_context(settings, engine, 3, context.survey_id), {})
    assert map_points(again["files"]["cleaned"]) == cleaned_before
    assert again["metrics"] is not None  # the simulator's reference labels: the paper's metrics


def test_semantickitti_labels_of_a_real_run(ran: dict, tmp_path: Path) -> None:
    """The SemanticKITTI export of the run (issue 20): one word per point of every frame, read
    back by the SemanticKITTI reader; every point the run removed carries a class, a moving
    object's points a moving id, the points it kept no moving id."""
    context, survey, result = ran["context"], ran["survey"], ran["result"]
    settings = ran["settings"]
    now = datetime.now(UTC)
    with Session(context.engine) as session:
        session.add(
            Job(survey_id=context.survey_id, kind="run:clutter", status=JobStatus.succeeded,
                result=result, started_at=now, finished_at=now)
        )  # fmt: skip
        session.commit()
        record = session.get(Survey, context.survey_id)
        decisions = review_decisions(session, context.survey_id)
        _, states = list_instances(session, context.survey_id, limit=1000)
        manifest = write_semantickitti_zip(session, settings, record, tmp_path / "labels.zip")
    assert all(d[2] == Decision.pending for d in decisions)  # the pipeline's own flags
    with zipfile.ZipFile(tmp_path / "labels.zip") as zf:
        zf.extractall(tmp_path)
    sequence = tmp_path / "sequences" / slug(record.name) / "labels"
    assert len(manifest["frames"]) == len(survey.frames)
    moving_ids = set(MOVING_OFFSET.values())
    moving = {(s.frame_id, s.instance_index) for s in states if s.moving}
    removed_total = 0
    for frame in survey.frames:
        read = read_label_file(sequence / f"{frame.frame_id}.label", frame.point_count)
        semantic = read["semantic"]
        removed = np.load(Path(result["files"]["labels"]) / f"{frame.frame_id}.npy").astype(bool)
        owner = np.load(Path(result["files"]["instances"]) / f"{frame.frame_id}.npz")["instance"]
        assert (semantic[removed] > 0).all()
        assert not np.isin(semantic[~removed], list(moving_ids)).any()
        mine = np.array([(frame.frame_id, int(k)) in moving for k in range(owner.max() + 1)])
        if len(mine):
            of_moving = removed & (owner >= 0) & mine[np.maximum(owner, 0)]
            assert np.isin(semantic[of_moving], list(moving_ids)).all()
        assert (read["instance"][removed] > 0).all()
        removed_total += int(removed.sum())
    assert removed_total > 0 and sum(manifest["points_per_id"].values()) >= removed_total


def test_bad_config_names_the_field(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "var")
    context = job_context(settings, None, 1, 1)
    with pytest.raises(ConfigError, match="^config.mode:"):
        run_clutter_task(context, {"mode": "everything"})
    with pytest.raises(ConfigError, match="^config.padding:"):
        run_clutter_task(context, {"padding": 3})
    with pytest.raises(ConfigError, match="^config.dufomap_d_p:"):
        run_clutter_task(context, {"dufomap_d_p": -1})
    with pytest.raises(ConfigError, match="^config.force:"):
        recompute_clutter(context, {"force": True})


def test_rerun_replaces_the_instances(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    init_db(engine)
    with Session(engine) as session:
        session.add(Survey(id=1, name="s", format="sim", source_path="/nowhere"))
        session.commit()
    row = {"class_name": "car", "point_count": 5, "mask_path": None, "bbox": [1, 2, 3, 4]}
    with Session(engine) as session:
        replace_instances(session, 1, [{**row, "frame_id": "a", "instance_index": 0}], None)
        replace_instances(
            session,
            1,
            [{**row, "frame_id": "b", "instance_index": i} for i in range(3)],
            None,
        )
        instances = session.exec(select(ClutterInstance)).all()
        assert sorted((i.frame_id, i.instance_index) for i in instances) == [
            ("b", 0),
            ("b", 1),
            ("b", 2),
        ]
        decisions = session.exec(select(ClutterDecision)).all()
        assert len(decisions) == 3 and {d.decision for d in decisions} == {Decision.pending}
        assert [d[:3] for d in review_decisions(session, 1)][0][2] == Decision.pending
        assert instances[0].bbox == [1, 2, 3, 4]
    engine.dispose()


def test_a_decision_during_a_batch_waits_for_it_and_is_then_stale(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another reviewer decides right after this batch's version check: the check and the
    update are one transaction, so the other decision waits for the batch, then finds the
    version it saw gone (409 with the batch's decision as `current`); nothing is lost."""
    engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    init_db(engine)
    with Session(engine) as session:
        session.add(Survey(id=1, name="s", format="sim", source_path="/nowhere"))
        session.commit()
        row = {"frame_id": "a", "class_name": "car", "point_count": 5}
        replace_instances(session, 1, [{**row, "instance_index": i} for i in range(2)], None)
        first, second = session.exec(select(ClutterInstance.id)).all()
    check = clutter_review._states
    other_result: list[BaseException | None] = []
    other: list[threading.Thread] = []

    def rival() -> None:
        try:
            with Session(engine) as session:
                decide(session, 1, [DecisionWrite(first, 1, Decision.rejected)], None)
            other_result.append(None)
        except BaseException as exc:  # the test inspects it
            other_result.append(exc)

    def check_then_race(session: Session, survey_id: int, ids: list[int]):
        states = check(session, survey_id, ids)
        if not other:
            other.append(threading.Thread(target=rival))
            other[0].start()
            other[0].join(timeout=0.5)  # it must still be waiting for this batch
            assert other[0].is_alive()
        return states

    monkeypatch.setattr(clutter_review, "_states", check_then_race)
    writes = [DecisionWrite(i, 1, Decision.approved) for i in (first, second)]
    with Session(engine) as session:
        decide(session, 1, writes, None)
    other[0].join(timeout=30)
    (stale,) = other_result
    assert isinstance(stale, StaleWriteError)
    assert [(c["instance_id"], c["decision"], c["version"]) for c in stale.current] == [
        (first, "approved", 2)
    ]
    with Session(engine) as session:
        _, states = list_instances(session, 1)
    assert [(s.decision, s.version) for s in states] == [
        (Decision.approved, 2),
        (Decision.approved, 2),
    ]
    engine.dispose()
