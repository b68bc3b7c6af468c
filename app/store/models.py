"""SQLModel tables: everything mmsclean remembers between runs.

One table per record kind; the shape follows fastapi/full-stack-fastapi-template (`models.py`).
Conventions every table keeps (the column types and shared columns: `app.store.columns`):

- Explicit snake_case table names; integer ids, timestamps and versions from `app.store.columns`.
- Records a user edits (users, surveys, labels, decisions, slices, guardrail models, model
  versions) are `Versioned` (optimistic concurrency, see `app.store.columns`). `Job` has no
  version: workers write its progress while users only cancel it.
- The API's `XPublic` shapes are read from rows by attribute. Where the columns it shows follow
  the table's own in schema order, they live in an `XBase` the table and `XPublic` both inherit
  (full-stack-fastapi-template's Base / table / Public); a base never reorders a table's columns.
- Children of a survey go with it (`ON DELETE CASCADE`); references to users, jobs and model
  versions become NULL instead.
- `Frame.pose` is the 4x4 sensor-to-world matrix in row-major order (16 floats, float64 exact
  through JSON); `Survey.origin_*` is the float64 local origin subtracted before float32 work.
"""

import enum
from datetime import datetime
from typing import Any, Optional

import sqlalchemy as sa
from sqlmodel import Field, Relationship, SQLModel

from app.store.columns import (
    Created,
    JSONDict,
    JSONList,
    Record,
    Timestamped,
    UTCDateTime,
    Versioned,
    enum_type,
    survey_fk,
    user_fk,
    utcnow,
)

# --- enums -------------------------------------------------------------------------------


class Role(enum.StrEnum):
    annotator = "annotator"
    reviewer = "reviewer"
    admin = "admin"


class JobStatus(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"
    interrupted = "interrupted"  # the worker died (server restart); may be resumed

    @property
    def finished(self) -> bool:
        return self in (JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled)


class LabelSource(enum.StrEnum):
    human = "human"
    model = "model"


class Decision(enum.StrEnum):
    pending = "pending"
    approved = "approved"
    rejected = "rejected"


class GuardrailKind(enum.StrEnum):
    pipe = "pipe"
    beam = "beam"


class ModelStatus(enum.StrEnum):
    pending = "pending"
    approved = "approved"
    rejected = "rejected"


class EditState(enum.StrEnum):
    """Where a batch of label edits stands on its user's undo / redo stack."""

    done = "done"
    undone = "undone"
    discarded = "discarded"  # undone, then buried under a newer edit: no longer redoable


class Pipeline(enum.StrEnum):
    phantom = "phantom"
    guardrail = "guardrail"
    clutter = "clutter"


class AreaState(enum.StrEnum):
    """Where a work area stands: open (being labelled) -> labelled (its annotator says done) ->
    signed_off (a reviewer accepted it), or back to open (a reviewer rejected it)."""

    open = "open"
    labelled = "labelled"
    signed_off = "signed_off"


# --- tables ------------------------------------------------------------------------------


class User(Versioned, table=True):
    __tablename__ = "user"

    username: str = Field(max_length=64, unique=True, index=True)
    hashed_password: str
    role: Role = Field(default=Role.annotator, sa_type=enum_type(Role), nullable=False)
    is_active: bool = Field(default=True)


class AuthSession(Created, table=True):
    """One login: its id rides in the signed token and is checked on every request, so logout,
    revocation and changes to the user end it at once. AUTOINCREMENT: an ended session's id is
    never handed out again (its old token must not come back to life)."""

    __tablename__ = "auth_session"
    __table_args__ = (
        sa.Index("ix_auth_session_user", "user_id", "ended_at"),
        {"sqlite_autoincrement": True},
    )

    user_id: int = Field(foreign_key="user.id", ondelete="CASCADE", nullable=False)
    expires_at: datetime = Field(sa_type=UTCDateTime, nullable=False)
    last_seen_at: datetime = Field(default_factory=utcnow, sa_type=UTCDateTime, nullable=False)
    ended_at: datetime | None = Field(default=None, sa_type=UTCDateTime)
    end_reason: str | None = Field(default=None, max_length=32)  # logout, revoked, password, ...
    client_address: str | None = Field(default=None, max_length=64)
    user_agent: str | None = Field(default=None, max_length=255)


class LoginThrottle(Record, table=True):
    """Recent failed logins of one user name or one client address, and its lock-out."""

    __tablename__ = "login_throttle"
    __table_args__ = (sa.UniqueConstraint("kind", "key", name="uq_login_throttle_key"),)

    kind: str = Field(max_length=16)  # "user" or "address"
    key: str = Field(max_length=255)
    failures: int = Field(default=0, ge=0)
    last_failure_at: datetime = Field(sa_type=UTCDateTime, nullable=False)
    locked_until: datetime | None = Field(default=None, sa_type=UTCDateTime)


class SurveyBase(Versioned):
    """A survey's columns the API shows as they are (`SurveyPublic`)."""

    name: str = Field(max_length=255, index=True)
    format: str = Field(max_length=32)  # reader name: kitti-raw, semantickitti, las, ply, pcd, sim
    source_path: str
    frame_count: int = Field(default=0, ge=0)
    point_count: int = Field(default=0, ge=0, sa_type=sa.BigInteger)
    has_reference_labels: bool = Field(default=False)
    poses_estimated: bool = Field(default=False)  # poses came from odometry, not GNSS/INS


class Survey(SurveyBase, table=True):
    __tablename__ = "survey"

    origin_x: float = Field(default=0.0, sa_type=sa.Double)
    origin_y: float = Field(default=0.0, sa_type=sa.Double)
    origin_z: float = Field(default=0.0, sa_type=sa.Double)
    created_by: int | None = user_fk()
    # rotating / profile / unknown (app.core.sensors): which models may run on it
    sensor_kind: str = Field(
        default="unknown", max_length=16, sa_column_kwargs={"server_default": "unknown"}
    )
    sensor_note: str = Field(  # how the kind was told: the reader, the point times, a person
        default="", max_length=255, sa_column_kwargs={"server_default": ""}
    )

    @property
    def origin(self) -> tuple[float, float, float]:
        """The local origin (x, y, z), float64."""
        return (self.origin_x, self.origin_y, self.origin_z)


class Frame(Created, table=True):
    __tablename__ = "frame"
    __table_args__ = (sa.UniqueConstraint("survey_id", "frame_id", name="uq_frame_survey_frame"),)

    survey_id: int = survey_fk()
    frame_index: int = Field(default=0, ge=0)  # position in the survey's frame order
    frame_id: str = Field(max_length=64)  # e.g. "000042"; "map" for an accumulated map
    timestamp: float | None = Field(default=None, sa_type=sa.Double)  # seconds
    point_count: int = Field(default=0, ge=0, sa_type=sa.BigInteger)
    pose: list[float] = Field(sa_type=JSONList, nullable=False)  # 4x4 row-major


class Job(Timestamped, table=True):
    __tablename__ = "job"
    __table_args__ = (
        sa.CheckConstraint("progress >= 0 AND progress <= 1", name="ck_job_progress"),
        sa.Index("ix_job_status_created", "status", "created_at"),
    )

    survey_id: int | None = Field(
        default=None, foreign_key="survey.id", ondelete="SET NULL", index=True
    )
    kind: str = Field(max_length=64, index=True)  # "run:phantom", "train:phantom", "import", ...
    config: dict[str, Any] = Field(default_factory=dict, sa_type=JSONDict, nullable=False)
    status: JobStatus = Field(
        default=JobStatus.queued, sa_type=enum_type(JobStatus), nullable=False
    )
    progress: float = Field(default=0.0, ge=0.0, le=1.0)
    message: str = Field(default="")
    log_path: str | None = None
    result_path: str | None = None
    created_by: int | None = user_fk()
    started_at: datetime | None = Field(default=None, sa_type=UTCDateTime)
    finished_at: datetime | None = Field(default=None, sa_type=UTCDateTime)
    worker_pid: int | None = None
    cancel_requested: bool = Field(default=False)  # the worker stops at its next progress call
    attempts: int = Field(default=0, ge=0)  # times a worker started it (resumes count)
    result: dict[str, Any] = Field(default_factory=dict, sa_type=JSONDict, nullable=False)


class ModelVersionBase(Created):
    """A model version's columns the API shows (`ModelVersionPublic`); the table adds
    `Versioned`'s after `created_at` (column order is the schema's)."""

    pipeline: Pipeline = Field(sa_type=enum_type(Pipeline), nullable=False, index=True)
    name: str = Field(max_length=128)
    checkpoint_path: str
    metrics: dict[str, Any] = Field(default_factory=dict, sa_type=JSONDict, nullable=False)
    trained_on: dict[str, Any] = Field(default_factory=dict, sa_type=JSONDict, nullable=False)
    is_promoted: bool = Field(default=False, index=True)
    job_id: int | None = Field(default=None, foreign_key="job.id", ondelete="SET NULL")


class ModelVersion(ModelVersionBase, Versioned, table=True):
    __tablename__ = "model_version"
    __table_args__ = (sa.UniqueConstraint("pipeline", "name", name="uq_model_version_name"),)

    # the scanner kind it was trained for; one promoted version per pipeline and kind
    sensor_kind: str = Field(
        default="profile", max_length=16, sa_column_kwargs={"server_default": "profile"}
    )


class PillarLabel(Versioned, table=True):
    """One pillar's label from one source; `cell_id` is the signed int64 packed pillar id."""

    __tablename__ = "pillar_label"
    __table_args__ = (
        sa.UniqueConstraint("survey_id", "cell_id", "source", name="uq_pillar_label_cell_source"),
        sa.CheckConstraint("label >= 0 AND label <= 3", name="ck_pillar_label_label"),
        sa.CheckConstraint(
            "confidence IS NULL OR (confidence >= 0 AND confidence <= 1)",
            name="ck_pillar_label_confidence",
        ),
        # covering index: tile reads never touch the table rows
        sa.Index(
            "ix_pillar_label_tile",
            "survey_id",
            "cell_id",
            "source",
            "label",
            "version",
            "confidence",
            "user_id",
        ),
        sa.Index("ix_pillar_label_source_updated", "source", "updated_at"),
    )

    survey_id: int = survey_fk()
    cell_id: int = Field(sa_type=sa.BigInteger, nullable=False)
    label: int = Field(ge=0, le=3)  # app.core.labels.PillarClass
    source: LabelSource = Field(sa_type=enum_type(LabelSource), nullable=False)
    confidence: float | None = Field(default=None, ge=0.0, le=1.0)
    user_id: int | None = user_fk()
    model_version_id: int | None = Field(
        default=None, foreign_key="model_version.id", ondelete="SET NULL"
    )


class PillarEditBatch(Created, table=True):
    """One labelling action of one user (a brush stroke, a rectangle): the unit of undo / redo."""

    __tablename__ = "pillar_edit_batch"
    __table_args__ = (sa.Index("ix_pillar_edit_batch_user", "user_id", "survey_id", "state"),)

    survey_id: int = survey_fk()
    user_id: int | None = user_fk()
    state: EditState = Field(default=EditState.done, sa_type=enum_type(EditState), nullable=False)
    size: int = Field(default=0, ge=0)


class PillarEdit(Record, table=True):
    """One pillar's human label before and after a batch (None: no human label)."""

    __tablename__ = "pillar_edit"
    # the edits that expect a pillar's version, found when an undo / redo restores it
    __table_args__ = (sa.Index("ix_pillar_edit_cell_version", "cell_id", "version"),)

    batch_id: int = Field(foreign_key="pillar_edit_batch.id", ondelete="CASCADE", index=True)
    cell_id: int = Field(sa_type=sa.BigInteger, nullable=False)
    before_label: int | None = None
    after_label: int | None = None
    # Versions (None: written before schema version 4, checked by label instead): `version` is
    # the one this edit's latest step (write, undo, redo) left, which its next undo / redo
    # expects; `version_before` is the one that step replaced, whose content the next step
    # restores (see app.store.versions).
    version: int | None = None
    version_before: int | None = None


class PillarTombstone(SQLModel, table=True):
    """An erased human pillar label. An erase is a new version of the pillar, not the end of its
    history: the next label written there takes version + 1 and replaces the tombstone, so a
    version a client once saw never comes back with another label (no ABA)."""

    __tablename__ = "pillar_tombstone"
    __table_args__ = {"sqlite_with_rowid": False}  # clustered on the key: tile reads scan it

    survey_id: int = Field(foreign_key="survey.id", ondelete="CASCADE", primary_key=True)
    cell_id: int = Field(sa_type=sa.BigInteger, primary_key=True)
    version: int = Field(ge=1)
    user_id: int | None = user_fk()  # who erased it
    updated_at: datetime = Field(default_factory=utcnow, sa_type=UTCDateTime, nullable=False)


class IssuedId(SQLModel, table=True):
    """The highest id ever handed out in a table whose rows a run replaces wholesale (clutter
    instances, guardrail slices and models). SQLite hands the highest id out again once its row
    is deleted; a client still holding (old id, version 1) would then write to a new row."""

    __tablename__ = "issued_id"

    name: str = Field(primary_key=True, max_length=64)  # the table
    last_id: int = Field(ge=0)


class ClutterInstance(Created, table=True):
    """One segmented object instance (person, car, ...) in one frame's camera image."""

    __tablename__ = "clutter_instance"
    __table_args__ = (
        sa.UniqueConstraint(
            "survey_id", "frame_id", "instance_index", name="uq_clutter_instance_index"
        ),
    )

    survey_id: int = survey_fk()
    frame_id: str = Field(max_length=64)  # Frame.frame_id within the survey
    instance_index: int = Field(ge=0)
    class_name: str = Field(max_length=32, index=True)
    point_count: int = Field(default=0, ge=0)
    mask_path: str | None = None
    bbox: list[int] | None = Field(default=None, sa_type=JSONList)  # [u0, v0, u1, v1] pixels
    moving: bool | None = None
    track_id: int | None = None

    decision: Optional["ClutterDecision"] = Relationship(
        back_populates="instance",
        sa_relationship_kwargs={
            "uselist": False,
            "cascade": "all, delete-orphan",
            "passive_deletes": True,
        },
    )


class ClutterDecision(Versioned, table=True):
    """The reviewer's verdict on a ClutterInstance: remove its points (approved) or keep them."""

    __tablename__ = "clutter_decision"

    instance_id: int = Field(
        foreign_key="clutter_instance.id", ondelete="CASCADE", unique=True, index=True
    )
    decision: Decision = Field(
        default=Decision.pending, sa_type=enum_type(Decision), nullable=False, index=True
    )
    user_id: int | None = user_fk()
    decided_at: datetime | None = Field(default=None, sa_type=UTCDateTime)

    instance: ClutterInstance = Relationship(back_populates="decision")


class ClutterCorrection(Created, table=True):
    """A reviewer's correction of a clutter instance's points (`app.store.clutter_corrections`):
    `remove` takes `points` out of the instance (they are kept), `add` made the instance (a
    missed object) of `points`. Applied in id order over the run's membership."""

    __tablename__ = "clutter_correction"
    __table_args__ = (sa.Index("ix_clutter_correction_frame", "survey_id", "frame_id"),)

    survey_id: int = survey_fk()
    frame_id: str = Field(max_length=64)
    instance_id: int = Field(foreign_key="clutter_instance.id", ondelete="CASCADE", index=True)
    kind: str = Field(max_length=16)  # "remove" | "add"
    points: bytes = Field(sa_type=sa.LargeBinary, nullable=False)  # int32 point indices, sorted
    point_count: int = Field(ge=0)
    user_id: int | None = user_fk()


class GuardrailSliceBase(Record):
    """A slice's columns the API shows (`GuardrailSlicePublic`); the table adds `Versioned`'s
    after `id` (column order is the schema's)."""

    survey_id: int = survey_fk()
    slice_index: int
    component_id: int
    station_m: float = Field(sa_type=sa.Double)  # distance along the trajectory
    predicted_label: int = Field(ge=0, le=1)  # CNN: 1 guardrail
    probability: float | None = Field(default=None, ge=0.0, le=1.0)
    corrected_label: int | None = Field(default=None, ge=0, le=1)  # after adjacency correction
    label: int = Field(ge=0, le=1)  # current label (human when labelled_by is set)
    labelled_by: int | None = user_fk()


class GuardrailSlice(GuardrailSliceBase, Versioned, table=True):
    """A 0.5 m slice of a roadside component: CNN prediction, adjacency correction, human label."""

    __tablename__ = "guardrail_slice"
    __table_args__ = (
        sa.UniqueConstraint(
            "survey_id", "component_id", "slice_index", name="uq_guardrail_slice_index"
        ),
        sa.CheckConstraint("predicted_label IN (0, 1)", name="ck_guardrail_slice_predicted"),
        sa.CheckConstraint(
            "corrected_label IS NULL OR corrected_label IN (0, 1)",
            name="ck_guardrail_slice_corrected",
        ),
        sa.CheckConstraint("label IN (0, 1)", name="ck_guardrail_slice_label"),
        sa.CheckConstraint(
            "probability IS NULL OR (probability >= 0 AND probability <= 1)",
            name="ck_guardrail_slice_probability",
        ),
    )


class GuardrailModel(Versioned, table=True):
    """One reconstructed guardrail (pipe or beam) awaiting review before export."""

    __tablename__ = "guardrail_model"
    __table_args__ = (
        sa.UniqueConstraint("survey_id", "guardrail_index", name="uq_guardrail_model_index"),
    )

    survey_id: int = survey_fk()
    guardrail_index: int = Field(ge=0)
    kind: GuardrailKind = Field(sa_type=enum_type(GuardrailKind), nullable=False)
    mesh_path: str
    params: dict[str, Any] = Field(default_factory=dict, sa_type=JSONDict, nullable=False)
    unit_count: int = Field(default=0, ge=0)
    icp_residual: float | None = None
    status: ModelStatus = Field(
        default=ModelStatus.pending, sa_type=enum_type(ModelStatus), nullable=False, index=True
    )
    decided_by: int | None = user_fk()
    decided_at: datetime | None = Field(default=None, sa_type=UTCDateTime)


class WorkAreaBase(Versioned):
    """A work area's columns the API shows as they are (`WorkAreaPublic`)."""

    survey_id: int = survey_fk()
    area_index: int = Field(ge=0)  # along the drive, from 0
    station_start: float = Field(sa_type=sa.Double)  # metres along the survey's frame poses
    station_end: float = Field(sa_type=sa.Double)
    # world bounding box of its pillars (float64; the trajectory piece's when it has none)
    x_min: float = Field(sa_type=sa.Double)
    y_min: float = Field(sa_type=sa.Double)
    x_max: float = Field(sa_type=sa.Double)
    y_max: float = Field(sa_type=sa.Double)
    assignee_id: int | None = user_fk()  # the annotator who labels it
    reviewer_id: int | None = user_fk()  # the reviewer who signs it off (any reviewer: None)
    state: AreaState = Field(
        default=AreaState.open, sa_type=enum_type(AreaState), nullable=False, index=True
    )
    comment: str = Field(default="", max_length=1000)  # the last rejection's reason
    decided_by: int | None = user_fk()  # who signed it off or rejected it last
    decided_at: datetime | None = Field(default=None, sa_type=UTCDateTime)


class WorkArea(WorkAreaBase, table=True):
    """A stretch of a survey's drive that one annotator labels and a reviewer signs off (a CVAT
    job). A survey's areas are cut together (`app.review.work_areas`) and replaced together."""

    __tablename__ = "work_area"
    __table_args__ = (sa.UniqueConstraint("survey_id", "area_index", name="uq_work_area_index"),)


class AuditEvent(Record, table=True):
    """Who did what to which record; `payload` holds the details (e.g. before/after values)."""

    __tablename__ = "audit_event"
    __table_args__ = (sa.Index("ix_audit_event_entity", "entity", "entity_id"),)

    at: datetime = Field(default_factory=utcnow, sa_type=UTCDateTime, nullable=False, index=True)
    user_id: int | None = user_fk(index=True)
    action: str = Field(max_length=64, index=True)  # e.g. "pillar.label", "clutter.approve"
    entity: str = Field(max_length=64)  # table name, e.g. "pillar_label"
    entity_id: str | None = Field(default=None, max_length=64)
    payload: dict[str, Any] = Field(default_factory=dict, sa_type=JSONDict, nullable=False)


TABLES: tuple[type[SQLModel], ...] = (
    User,
    AuthSession,
    LoginThrottle,
    Survey,
    Frame,
    Job,
    ModelVersion,
    PillarLabel,
    PillarEditBatch,
    PillarEdit,
    PillarTombstone,
    IssuedId,
    ClutterInstance,
    ClutterDecision,
    ClutterCorrection,
    GuardrailSlice,
    GuardrailModel,
    WorkArea,
    AuditEvent,
)
