"""Correcting clutter instances, for the API and the viewer alike: read a frame's membership
from the survey's current clutter run, apply the reviewers' corrections to it, and write new
ones through the store (`app.store.clutter_corrections`, which checks them against the same
membership inside its write transaction).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from sqlmodel import Session

from app.core.errors import ConfigError, ConflictError
from app.geometry.projection import project
from app.io import open_survey
from app.pipelines.clutter.review_corrections import (
    ADD,
    REMOVE,
    MembershipCorrection,
    corrected_membership,
)
from app.review.box_objects import PixelBox, checked_box, object_in_box, run_camera, run_config
from app.store import clutter_corrections, clutter_review
from app.store.clutter_corrections import Corrected, RunMembership
from app.store.models import Survey as SurveyRecord

__all__ = [
    "ADD",
    "REMOVE",
    "Corrected",
    "MembershipCorrection",
    "RunMembership",
    "PixelBox",
    "add_object",
    "add_object_in_box",
    "corrected_membership",
    "frame_membership",
    "remove_points",
    "run_membership",
]


def run_membership(session: Session, survey_id: int, frame_id: str) -> RunMembership:
    """The frame's membership as the survey's current clutter run wrote it."""
    folder = clutter_corrections.current_run_folder(session, survey_id)
    if folder is None:
        raise ConflictError(f"survey {survey_id} has no clutter run to review; run clutter first")
    path = folder / "instances" / f"{frame_id}.npz"
    try:
        with np.load(path) as data:
            owner, flags = data["instance"].astype(np.int32), data["removed"].astype(bool)
    except (OSError, KeyError, ValueError):
        raise ConflictError(
            f"the clutter run in {folder} has no readable membership of frame {frame_id!r}; "
            "run clutter again"
        ) from None
    return RunMembership(folder, frame_id, owner, flags)


def frame_membership(
    session: Session, survey_id: int, membership: RunMembership
) -> tuple[np.ndarray, np.ndarray]:
    """(owner, removed flags) of the frame with the reviewers' corrections applied."""
    corrections = clutter_corrections.frame_corrections(session, survey_id, membership.frame_id)
    return corrected_membership(membership.owner, membership.flags, corrections)


def remove_points(
    session: Session,
    survey_id: int,
    instance_id: int,
    version: int,
    points: Sequence[int] | np.ndarray,
    user_id: int | None,
    membership: RunMembership | None = None,
) -> Corrected:
    """Take the instance's points among `points` out of it (see the store's `remove_points`);
    `membership`: the frame's, when the caller has read it already."""
    if membership is None:
        state = clutter_review.get_instance(session, survey_id, instance_id)
        membership = run_membership(session, survey_id, state.frame_id)
        session.rollback()  # end the read: the write takes its own lock and reads again
    return clutter_corrections.remove_points(
        session, survey_id, instance_id, version, points, membership, user_id
    )


def add_object(
    session: Session,
    survey_id: int,
    frame_id: str,
    class_name: str,
    points: Sequence[int] | np.ndarray,
    user_id: int | None,
    membership: RunMembership | None = None,
    bbox: list[int] | None = None,
) -> Corrected:
    """A missed object of `class_name` from the points among `points` that belong to no
    instance (see the store's `add_object`)."""
    if membership is None:
        clutter_corrections.check_frame(session, survey_id, frame_id)
        membership = run_membership(session, survey_id, frame_id)
        session.rollback()
    return clutter_corrections.add_object(
        session, survey_id, frame_id, class_name, points, membership, user_id, bbox
    )


def add_object_in_box(
    session: Session,
    survey_id: int,
    frame_id: str,
    class_name: str,
    box: PixelBox,
    user_id: int | None,
) -> Corrected:
    """A missed object outlined by a 2D box on the frame's camera image (the run's camera):
    `box_objects.object_in_box` finds its points, `add_object` writes them. ConfigError naming
    `box` when it covers no pixel of the image or no free object shows in it; ConflictError
    when the frame has no image of that camera."""
    clutter_corrections.check_frame(session, survey_id, frame_id)
    membership = run_membership(session, survey_id, frame_id)
    record = session.get(SurveyRecord, survey_id)
    session.rollback()
    survey = open_survey(record.source_path, record.format)
    frame = next((f for f in survey.frames if f.frame_id == frame_id), None)
    camera = run_camera(survey, membership.folder)
    if frame is None or camera is None or camera.name not in frame.image_paths:
        raise ConflictError(f"frame {frame_id!r} of survey {survey_id} has no camera image")
    box = checked_box(box, camera)
    xyz = frame.points().xyz
    owner, _ = frame_membership(session, survey_id, membership)
    session.rollback()
    if len(owner) != len(xyz):
        raise ConflictError(f"frame {frame_id!r}: the clutter run's membership is out of date")
    projection = project(xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)
    points = object_in_box(xyz, projection, owner, box, run_config(membership.folder))
    if not len(points):
        raise ConfigError(
            "box", "shows no object free of an instance above the ground (draw it round one)"
        )
    return add_object(
        session, survey_id, frame_id, class_name, points, user_id, membership, box.as_bbox()
    )
