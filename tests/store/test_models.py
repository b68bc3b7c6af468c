"""Every table: inserts with relations, cascades, constraints and value round trips."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError, StatementError
from sqlmodel import Session, func, select

from app.core.labels import PillarClass
from app.store.models import (
    TABLES,
    AuditEvent,
    AuthSession,
    ClutterCorrection,
    ClutterDecision,
    ClutterInstance,
    Decision,
    Frame,
    GuardrailKind,
    GuardrailModel,
    GuardrailSlice,
    IssuedId,
    Job,
    JobStatus,
    LabelSource,
    LoginThrottle,
    ModelStatus,
    ModelVersion,
    PillarEdit,
    PillarEditBatch,
    PillarLabel,
    PillarTombstone,
    Pipeline,
    Role,
    Survey,
    User,
    WorkArea,
)

IDENTITY = [float(v) for v in (1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1)]


def _survey(session: Session, name: str = "drive", user: User | None = None) -> Survey:
    survey = Survey(
        name=name,
        format="kitti-raw",
        source_path="/data/2011_09_26_drive_0001_sync",
        frame_count=2,
        point_count=240_000,
        has_reference_labels=True,
        origin_x=456_789.123_456_789,
        origin_y=5_432_109.987_654_321,
        origin_z=112.5,
        created_by=user.id if user else None,
    )
    session.add(survey)
    session.flush()
    return survey


def _populate(session: Session) -> dict[str, int]:
    """One row of every table, linked together; returns their ids."""
    user = User(username="ann", hashed_password="$argon2$x", role=Role.reviewer)
    session.add(user)
    session.flush()
    survey = _survey(session, user=user)
    frames = [
        Frame(
            survey_id=survey.id,
            frame_index=i,
            frame_id=f"{i:06d}",
            timestamp=1.5 * i,
            point_count=120_000,
            pose=IDENTITY,
        )
        for i in range(2)
    ]
    job = Job(survey_id=survey.id, kind="train:phantom", config={"epochs": 3}, created_by=user.id)
    session.add_all([*frames, job])
    session.flush()
    model = ModelVersion(
        pipeline=Pipeline.phantom,
        name="phantom-2024-01",
        checkpoint_path="models/p.pt",
        metrics={"f1": 0.93},
        trained_on={"surveys": [survey.id]},
        job_id=job.id,
    )
    session.add(model)
    session.flush()
    human = PillarLabel(
        survey_id=survey.id,
        cell_id=42,
        label=PillarClass.phantom,
        source=LabelSource.human,
        user_id=user.id,
    )
    predicted = PillarLabel(
        survey_id=survey.id,
        cell_id=42,
        label=PillarClass.short_object,
        source=LabelSource.model,
        confidence=0.8,
        model_version_id=model.id,
    )
    instance = ClutterInstance(
        survey_id=survey.id,
        frame_id="000001",
        instance_index=0,
        class_name="car",
        point_count=812,
        mask_path="masks/1_0.png",
        bbox=[10, 20, 110, 90],
        moving=True,
        track_id=5,
    )
    instance.decision = ClutterDecision(
        decision=Decision.approved, user_id=user.id, decided_at=datetime.now(UTC)
    )
    slice_ = GuardrailSlice(
        survey_id=survey.id,
        slice_index=3,
        component_id=1,
        station_m=1.5,
        predicted_label=1,
        probability=0.7,
        corrected_label=0,
        label=0,
        labelled_by=user.id,
    )
    rail = GuardrailModel(
        survey_id=survey.id,
        guardrail_index=0,
        kind=GuardrailKind.beam,
        mesh_path="meshes/0.ply",
        params={"section": [[0, 0], [0.3, 0.1]]},
        unit_count=4,
        icp_residual=0.004,
    )
    event = AuditEvent(
        user_id=user.id,
        action="pillar.label",
        entity="pillar_label",
        entity_id="1",
        payload={"before": None, "after": 3},
    )
    batch = PillarEditBatch(survey_id=survey.id, user_id=user.id, size=1)
    session.add_all([human, predicted, instance, slice_, rail, event, batch])
    session.flush()
    session.add(PillarEdit(batch_id=batch.id, cell_id=42, before_label=None, after_label=3))
    points = np.array([3, 5, 8], dtype=np.int32)
    session.add(
        ClutterCorrection(
            survey_id=survey.id, frame_id="000001", instance_id=instance.id, kind="remove",
            points=points.tobytes(), point_count=len(points), user_id=user.id,
        )
    )  # fmt: skip
    session.add(
        WorkArea(
            survey_id=survey.id, area_index=0, station_start=0.0, station_end=100.0,
            x_min=0.0, y_min=0.0, x_max=100.0, y_max=20.0, assignee_id=user.id,
        )
    )  # fmt: skip
    session.add(PillarTombstone(survey_id=survey.id, cell_id=43, version=2, user_id=user.id))
    session.add(IssuedId(name="clutter_instance", last_id=7))
    now = datetime.now(UTC)
    session.add(AuthSession(user_id=user.id, expires_at=now + timedelta(hours=1)))
    session.add(LoginThrottle(kind="user", key="ann", failures=1, last_failure_at=now))
    session.commit()
    return {
        "user": user.id,
        "survey": survey.id,
        "job": job.id,
        "model": model.id,
        "instance": instance.id,
        "decision": instance.decision.id,
        "event": event.id,
    }


def _count(session: Session, table: type) -> int:
    return session.exec(select(func.count()).select_from(table)).one()


def test_one_row_of_every_table_with_relations(session: Session) -> None:
    ids = _populate(session)
    session.expire_all()
    for table in TABLES:
        assert _count(session, table) >= 1, table.__name__
    decision = session.get(ClutterDecision, ids["decision"])
    assert decision.instance.class_name == "car"
    assert decision.decision is Decision.approved
    assert session.get(ClutterInstance, ids["instance"]).decision.id == ids["decision"]
    label = session.exec(select(PillarLabel).where(PillarLabel.source == "model")).one()
    assert label.model_version_id == ids["model"] and label.label == 2
    job = session.get(Job, ids["job"])
    assert job.status is JobStatus.queued and job.progress == 0.0 and job.message == ""
    assert session.get(GuardrailModel, 1).status is ModelStatus.pending
    assert session.get(User, ids["user"]).role is Role.reviewer


def test_deleting_a_survey_deletes_its_frames_labels_and_results(session: Session) -> None:
    ids = _populate(session)
    other = _survey(session, name="other")
    session.add(Frame(survey_id=other.id, frame_id="map", point_count=1, pose=IDENTITY))
    session.commit()

    session.delete(session.get(Survey, ids["survey"]))
    session.commit()
    session.expire_all()

    for table in (
        PillarLabel,
        PillarTombstone,
        ClutterInstance,
        ClutterDecision,
        GuardrailSlice,
        GuardrailModel,
    ):
        assert _count(session, table) == 0, table.__name__
    assert session.exec(select(Frame.frame_id)).all() == ["map"]  # the other survey's frame
    # history outlives the survey: the job and model version stay, unlinked
    assert session.get(Job, ids["job"]).survey_id is None
    assert session.get(ModelVersion, ids["model"]) is not None


def test_deleting_a_user_keeps_their_work_unattributed(session: Session) -> None:
    ids = _populate(session)
    session.delete(session.get(User, ids["user"]))
    session.commit()
    session.expire_all()
    assert session.get(Survey, ids["survey"]).created_by is None
    assert session.exec(select(PillarLabel.user_id)).all() == [None, None]
    assert session.get(AuditEvent, ids["event"]).user_id is None


def test_deleting_an_instance_deletes_its_decision(session: Session) -> None:
    ids = _populate(session)
    session.delete(session.get(ClutterInstance, ids["instance"]))
    session.commit()
    assert _count(session, ClutterDecision) == 0


def test_foreign_keys_are_enforced(session: Session) -> None:
    session.add(Frame(survey_id=999, frame_id="000000", pose=IDENTITY))
    with pytest.raises(IntegrityError, match="FOREIGN KEY"):
        session.commit()


def test_duplicate_pillar_label_for_the_same_cell_and_source_is_refused(session: Session) -> None:
    survey = _survey(session)
    session.add_all(
        [
            PillarLabel(survey_id=survey.id, cell_id=1, label=0, source=LabelSource.human),
            PillarLabel(survey_id=survey.id, cell_id=1, label=0, source=LabelSource.model),
        ]
    )
    session.commit()  # same cell, different sources: fine
    session.add(PillarLabel(survey_id=survey.id, cell_id=1, label=3, source=LabelSource.human))
    with pytest.raises(IntegrityError, match="UNIQUE"):
        session.commit()


@pytest.mark.parametrize(
    "make",
    [
        lambda s: [
            User(username="ann", hashed_password="a"),
            User(username="ann", hashed_password="b"),
        ],
        lambda s: [Frame(survey_id=s, frame_id="000001", pose=IDENTITY) for _ in range(2)],
        lambda s: [
            ClutterInstance(survey_id=s, frame_id="1", instance_index=0, class_name="car")
            for _ in range(2)
        ],
        lambda s: [
            GuardrailSlice(
                survey_id=s,
                slice_index=0,
                component_id=0,
                station_m=0.0,
                predicted_label=0,
                label=0,
            )
            for _ in range(2)
        ],
        lambda s: [
            GuardrailModel(survey_id=s, guardrail_index=0, kind="pipe", mesh_path="m")
            for _ in range(2)
        ],
        lambda s: [
            ModelVersion(pipeline="clutter", name="m", checkpoint_path="c") for _ in range(2)
        ],
    ],
    ids=["username", "frame", "clutter_instance", "guardrail_slice", "guardrail_model", "model"],
)
def test_unique_constraints(session: Session, make) -> None:
    survey = _survey(session)
    first, second = make(survey.id)
    session.add(first)
    session.commit()
    session.add(second)
    with pytest.raises(IntegrityError, match="UNIQUE"):
        session.commit()


def test_one_decision_per_instance(session: Session) -> None:
    survey = _survey(session)
    instance = ClutterInstance(survey_id=survey.id, frame_id="1", instance_index=0, class_name="x")
    session.add(instance)
    session.flush()
    session.add_all([ClutterDecision(instance_id=instance.id) for _ in range(2)])
    with pytest.raises(IntegrityError, match="UNIQUE"):
        session.commit()


@pytest.mark.parametrize(
    ("table", "fields"),
    [
        (PillarLabel, {"cell_id": 1, "label": 4, "source": "human"}),
        (PillarLabel, {"cell_id": 1, "label": -1, "source": "human"}),
        (PillarLabel, {"cell_id": 1, "label": 1, "source": "model", "confidence": 1.5}),
        (
            GuardrailSlice,
            {
                "slice_index": 0,
                "component_id": 0,
                "station_m": 0.0,
                "predicted_label": 2,
                "label": 0,
            },
        ),
        (
            GuardrailSlice,
            {
                "slice_index": 0,
                "component_id": 0,
                "station_m": 0.0,
                "predicted_label": 0,
                "label": 0,
                "corrected_label": 5,
            },
        ),
        (Job, {"kind": "run:phantom", "progress": 1.2}),
    ],
)
def test_out_of_range_values_are_refused_by_the_database(
    session: Session, table: type, fields: dict
) -> None:
    survey = _survey(session)
    session.add(table(survey_id=survey.id, **fields))
    with pytest.raises(IntegrityError, match="CHECK"):
        session.commit()


def test_unknown_enum_value_is_refused(session: Session) -> None:
    session.add(User(username="ann", hashed_password="x", role="superuser"))
    with pytest.raises(StatementError, match="superuser"):
        session.commit()


def test_enums_are_stored_as_their_values(session: Session, engine: Engine) -> None:
    ids = _populate(session)
    with engine.connect() as conn:
        row = conn.exec_driver_sql("SELECT status, config FROM job WHERE id = ?", (ids["job"],))
        assert row.one() == ("queued", '{"epochs": 3}')
        assert conn.exec_driver_sql("SELECT role FROM user").scalar() == "reviewer"


@pytest.mark.parametrize("cell_id", [2**63 - 1, -(2**63), 2**63 - 12345, 2**40 + 7])
def test_int64_cell_ids_round_trip(session: Session, engine: Engine, cell_id: int) -> None:
    survey = _survey(session)
    session.add(PillarLabel(survey_id=survey.id, cell_id=cell_id, label=1, source="human"))
    session.commit()
    session.expire_all()
    assert session.exec(select(PillarLabel.cell_id)).one() == cell_id
    found = session.exec(select(PillarLabel).where(PillarLabel.cell_id == cell_id)).one()
    assert found.cell_id == cell_id
    with engine.connect() as conn:
        assert (
            conn.exec_driver_sql("SELECT typeof(cell_id) FROM pillar_label").scalar() == "integer"
        )


def test_json_and_float64_fields_round_trip(session: Session) -> None:
    ids = _populate(session)
    pose = [0.1, -1e-17, 123456789.123456789, 2.0 / 3.0] + [float(i) for i in range(12)]
    frame = session.exec(select(Frame).where(Frame.frame_id == "000000")).one()
    frame.pose = pose
    session.commit()
    session.expire_all()

    assert session.exec(select(Frame.pose).where(Frame.frame_id == "000000")).one() == pose
    survey = session.get(Survey, ids["survey"])
    assert (survey.origin_x, survey.origin_y) == (456_789.123_456_789, 5_432_109.987_654_321)
    model = session.get(ModelVersion, ids["model"])
    assert model.metrics == {"f1": 0.93} and model.trained_on == {"surveys": [ids["survey"]]}
    rail = session.exec(select(GuardrailModel)).one()
    assert rail.params == {"section": [[0, 0], [0.3, 0.1]]}
    instance = session.get(ClutterInstance, ids["instance"])
    assert instance.bbox == [10, 20, 110, 90] and instance.moving is True
    assert session.get(AuditEvent, ids["event"]).payload == {"before": None, "after": 3}


def test_nullable_json_is_sql_null(session: Session, engine: Engine) -> None:
    survey = _survey(session)
    session.add(
        ClutterInstance(survey_id=survey.id, frame_id="1", instance_index=0, class_name="person")
    )
    session.commit()
    with engine.connect() as conn:
        assert conn.exec_driver_sql("SELECT bbox IS NULL FROM clutter_instance").scalar() == 1


def test_in_place_changes_to_json_dicts_are_saved(session: Session) -> None:
    ids = _populate(session)
    job = session.get(Job, ids["job"])
    job.config["epochs"] = 10
    session.commit()
    session.expire_all()
    assert session.get(Job, ids["job"]).config == {"epochs": 10}


def test_timestamps_are_utc_aware_and_updated_at_moves(session: Session) -> None:
    survey = _survey(session)
    session.commit()
    session.expire_all()
    survey = session.get(Survey, survey.id)
    assert survey.created_at.tzinfo is UTC and survey.updated_at.tzinfo is UTC
    assert abs(datetime.now(UTC) - survey.created_at) < timedelta(minutes=1)
    before = survey.updated_at
    survey.name = "renamed"
    session.commit()
    session.expire_all()
    survey = session.get(Survey, survey.id)
    assert survey.updated_at >= before and survey.created_at <= survey.updated_at
    assert survey.version == 2


def test_aware_times_in_other_zones_are_stored_as_utc(session: Session) -> None:
    tokyo = timezone(timedelta(hours=9))
    session.add(Job(kind="run:clutter", started_at=datetime(2024, 5, 1, 9, 0, tzinfo=tokyo)))
    session.commit()
    session.expire_all()
    assert session.exec(select(Job.started_at)).one() == datetime(2024, 5, 1, 0, 0, tzinfo=UTC)


def test_versions_bump_on_every_update(session: Session) -> None:
    ids = _populate(session)
    decision = session.get(ClutterDecision, ids["decision"])
    assert decision.version == 1
    decision.decision = Decision.rejected
    session.commit()
    decision.decision = Decision.pending
    session.commit()
    session.expire_all()
    assert session.get(ClutterDecision, ids["decision"]).version == 3
