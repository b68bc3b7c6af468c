"""Survey records: registering an opened survey (with its frames), reading, deleting.

Points stay in the source files; the store keeps one row per frame (pose, counts, time) so
lists and summaries never open a point file.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlmodel import Session, col, func, select

from app.core.errors import ConflictError, NotFoundError
from app.core.sensors import SensorKind
from app.io.sensor_kind import detect_sensor_kind
from app.store.audit import audit, unused_id
from app.store.db import commit
from app.store.models import Frame, Job, JobStatus, Survey

if TYPE_CHECKING:
    from app.io.survey import Survey as OpenedSurvey


@dataclass(frozen=True)
class FrameRecord:
    """What the store keeps of one frame (the points stay in the source files)."""

    frame_index: int
    frame_id: str
    timestamp: float | None
    point_count: int
    pose: list[float]  # 4x4 row-major


def frame_records(survey: OpenedSurvey) -> list[FrameRecord]:
    """The store's view of an opened survey's frames (no point file is read)."""
    return [
        FrameRecord(
            frame_index=f.index,
            frame_id=f.frame_id,
            timestamp=f.timestamp,
            point_count=int(f.point_count or 0),
            pose=[float(v) for v in np.asarray(f.pose, dtype=np.float64).ravel()],
        )
        for f in survey.frames
    ]


def survey_origin(survey: OpenedSurvey) -> tuple[float, float, float]:
    """The float64 local origin: the first sensor position of a drive; for a map its first
    trajectory pose, else its minimum corner in whole metres (LAS: from the header; PLY/PCD:
    from the points, read once at import)."""
    if not len(survey):
        return (0.0, 0.0, 0.0)
    if not survey.is_map:
        first = np.asarray(survey.frames[0].pose)[:3, 3]
    elif survey.trajectory is not None and len(survey.trajectory):
        first = np.asarray(survey.trajectory[0])[:3, 3]
    elif survey.format == "las":
        import laspy

        with laspy.open(survey.source) as reader:
            first = np.floor(np.asarray(reader.header.mins, dtype=np.float64))
    else:
        xyz = survey.frames[0].points().xyz
        first = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    return (float(first[0]), float(first[1]), float(first[2]))


def survey_count(session: Session) -> int:
    return int(session.exec(select(func.count()).select_from(Survey)).one())


def register_survey(
    session: Session,
    *,
    name: str,
    format: str,
    source_path: str,
    frames: Sequence[FrameRecord],
    has_reference_labels: bool,
    poses_estimated: bool,
    origin: tuple[float, float, float],
    created_by: int | None = None,
    action: str = "survey.register",
    sensor_kind: str = "unknown",
    sensor_note: str = "",
    **audit_payload: Any,
) -> Survey:
    """Insert a survey, all its frames and the audit event `action` in one transaction."""
    survey = Survey(
        name=name,
        format=format,
        source_path=source_path,
        frame_count=len(frames),
        point_count=sum(f.point_count for f in frames),
        has_reference_labels=has_reference_labels,
        poses_estimated=poses_estimated,
        origin_x=origin[0],
        origin_y=origin[1],
        origin_z=origin[2],
        created_by=created_by,
        sensor_kind=sensor_kind,
        sensor_note=sensor_note[:255],
    )
    survey.id = unused_id(Survey, "survey")  # type: ignore[assignment]
    session.add(survey)
    session.flush()
    session.add_all(
        Frame(
            survey_id=survey.id,
            frame_index=f.frame_index,
            frame_id=f.frame_id,
            timestamp=f.timestamp,
            point_count=f.point_count,
            pose=f.pose,
        )
        for f in frames
    )
    audit(
        session,
        created_by,
        action,
        "survey",
        survey.id,
        name=name,
        format=format,
        source_path=source_path,
        frames=len(frames),
        sensor_kind=sensor_kind,
        **audit_payload,
    )
    commit(session)
    session.refresh(survey)
    return survey


def register_opened_survey(
    session: Session,
    opened: OpenedSurvey,
    *,
    format: str,
    source_path: Path,
    name: str | None = None,
    created_by: int | None = None,
    action: str = "survey.register",
    sensor: SensorKind | None = None,
    **audit_payload: Any,
) -> Survey:
    """Register a survey a reader opened, with its frames, local origin and sensor kind (as
    `sensor` declares it, else as its reader or its point times tell)."""
    if sensor is not None and sensor is not SensorKind.UNKNOWN:
        kind, note = sensor, "declared at import"
    else:
        detection = detect_sensor_kind(opened)
        kind, note = detection.kind, detection.reason
    return register_survey(
        session,
        name=(name or opened.name or source_path.stem)[:255],
        format=format,
        source_path=str(source_path),
        frames=frame_records(opened),
        has_reference_labels=bool(opened.reference_label_kinds),
        poses_estimated=opened.poses_estimated,
        origin=survey_origin(opened),
        created_by=created_by,
        action=action,
        sensor_kind=kind.value,
        sensor_note=note,
        **audit_payload,
    )


def set_sensor_kind(
    session: Session, survey_id: int, kind: SensorKind, user_id: int | None, note: str
) -> Survey:
    """A survey's sensor kind as a person or a first run told it; audited, commits."""
    survey = get_survey(session, survey_id)
    before = survey.sensor_kind
    survey.sensor_kind, survey.sensor_note = kind.value, note[:255]
    session.add(survey)
    audit(session, user_id, "survey.sensor", "survey", survey_id, before=before, after=kind.value)
    commit(session)
    session.refresh(survey)
    return survey


def list_surveys(session: Session) -> list[Survey]:
    return list(session.exec(select(Survey).order_by(col(Survey.id))).all())


def find_survey(session: Session, key: str) -> Survey:
    """A survey by its id (digits) or its exact name; a name two surveys share is refused."""
    if key.isdigit():
        return get_survey(session, int(key))
    found = session.exec(select(Survey).where(Survey.name == key)).all()
    if not found:
        raise NotFoundError(f"no survey named {key!r}")
    if len(found) > 1:
        ids = ", ".join(str(s.id) for s in found)
        raise ConflictError(f"{len(found)} surveys are named {key!r} (ids {ids}); give the id")
    return found[0]


def get_survey(session: Session, survey_id: int) -> Survey:
    survey = session.get(Survey, survey_id)
    if survey is None:
        raise NotFoundError(f"survey {survey_id} not found")
    return survey


def survey_exists(session: Session, survey_id: int) -> bool:
    return session.get(Survey, survey_id) is not None


def frames_summary(session: Session, survey_id: int) -> dict[str, Any]:
    """Counts, point statistics, time span and driven length of a survey's frames."""
    rows = session.exec(
        select(Frame.frame_id, Frame.point_count, Frame.timestamp, Frame.pose)
        .where(Frame.survey_id == survey_id)
        .order_by(col(Frame.frame_index))
    ).all()
    if not rows:
        return {"count": 0, "points": 0}
    ids, counts, times, poses = zip(*rows, strict=True)
    counts_arr = np.asarray(counts, dtype=np.int64)
    stamps = np.asarray(times, dtype=np.float64)  # None -> NaN
    positions = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    finite = stamps[np.isfinite(stamps)]
    return {
        "count": len(ids),
        "points": int(counts_arr.sum()),
        "points_per_frame": {
            "min": int(counts_arr.min()),
            "mean": float(counts_arr.mean()),
            "max": int(counts_arr.max()),
        },
        "first_frame_id": ids[0],
        "last_frame_id": ids[-1],
        "start_time": float(finite.min()) if finite.size else None,
        "duration_s": float(finite.max() - finite.min()) if finite.size else None,
        "trajectory_length_m": float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()),
    }


@dataclass(frozen=True)
class SurveyFootprint:
    """How big a survey is, as far as the store knows: its points and frames and the bounding
    box of its trajectory (sensor positions). The extent of the points themselves is not
    stored; a job's memory estimate widens the trajectory by the sensor's reach instead."""

    points: int
    frames: int
    largest_frame: int  # points of the largest frame
    trajectory_min: tuple[float, float, float]
    trajectory_max: tuple[float, float, float]


def frame_point_counts(session: Session, survey_id: int) -> list[tuple[str, int]]:
    """(frame id, points) of the survey's frames in frame order."""
    rows = session.exec(
        select(Frame.frame_id, Frame.point_count)
        .where(Frame.survey_id == survey_id)
        .order_by(col(Frame.frame_index))
    ).all()
    return [(frame_id, int(count)) for frame_id, count in rows]


def survey_footprint(session: Session, survey_id: int) -> SurveyFootprint:
    """The survey's footprint from its frame rows (NotFoundError for an unknown survey)."""
    survey = get_survey(session, survey_id)
    rows = session.exec(
        select(Frame.point_count, Frame.pose).where(Frame.survey_id == survey_id)
    ).all()
    if not rows:
        origin = (survey.origin_x, survey.origin_y, survey.origin_z)
        return SurveyFootprint(survey.point_count, 0, survey.point_count, origin, origin)
    counts = np.asarray([r[0] for r in rows], dtype=np.int64)
    positions = np.asarray([r[1] for r in rows], dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    return SurveyFootprint(
        points=int(max(counts.sum(), survey.point_count)),
        frames=len(rows),
        largest_frame=int(counts.max()),
        trajectory_min=tuple(positions.min(axis=0).tolist()),
        trajectory_max=tuple(positions.max(axis=0).tolist()),
    )


def latest_jobs(session: Session, survey_id: int) -> dict[str, Job]:
    """The newest job of each kind run on the survey."""
    newest = (
        select(func.max(Job.id))
        .where(Job.survey_id == survey_id)
        .group_by(Job.kind)
        .scalar_subquery()
    )
    jobs = session.exec(select(Job).where(col(Job.id).in_(newest)).order_by(Job.kind)).all()
    return {job.kind: job for job in jobs}


def latest_succeeded_job(session: Session, survey_id: int, kinds: Iterable[str]) -> Job | None:
    """The newest succeeded job of one of `kinds` on the survey (by finish time, then id)."""
    return session.exec(
        select(Job)
        .where(
            Job.survey_id == survey_id,
            col(Job.kind).in_(list(kinds)),
            Job.status == JobStatus.succeeded,
        )
        .order_by(col(Job.finished_at).desc().nulls_last(), col(Job.id).desc())
        .limit(1)
    ).first()


def surveys_using(session: Session, folder: Path, exclude: int | None = None) -> list[int]:
    """Ids of surveys whose source lies in `folder` (an upload folder two surveys may share)."""
    prefix = str(folder).rstrip("/") + "/"
    query = select(Survey.id).where(
        (Survey.source_path == str(folder))
        | col(Survey.source_path).startswith(prefix, autoescape=True)
    )
    if exclude is not None:
        query = query.where(Survey.id != exclude)
    return list(session.exec(query).all())


def delete_survey(
    session: Session, survey_id: int, user_id: int | None, **audit_payload: Any
) -> Survey:
    """Delete a survey and (by cascade) its frames, labels, decisions and models; refused while
    one of its jobs is queued or running. Files are the caller's business."""
    survey = get_survey(session, survey_id)
    active = session.exec(
        select(Job.id).where(
            Job.survey_id == survey_id,
            col(Job.status).in_([JobStatus.queued, JobStatus.running]),
        )
    ).first()
    if active is not None:
        raise ConflictError(
            f"survey {survey_id} has job {active} queued or running; cancel it first"
        )
    audit(
        session,
        user_id,
        "survey.delete",
        "survey",
        survey_id,
        name=survey.name,
        format=survey.format,
        source_path=survey.source_path,
        frames=survey.frame_count,
        **audit_payload,
    )
    session.delete(survey)
    commit(session)
    return survey


def survey_trajectory(session: Session, survey_id: int) -> np.ndarray:
    """(M, 3) float64 world positions of the sensor, frame by frame in recorded order (its
    frames' poses; a map's one frame gives one position)."""
    poses = session.exec(
        select(Frame.pose).where(Frame.survey_id == survey_id).order_by(Frame.frame_index)
    ).all()
    return np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
