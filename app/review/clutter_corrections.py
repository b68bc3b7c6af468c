"""Correcting clutter instances, for the API and the viewer alike: read a frame's membership
from the survey's current clutter run, apply the reviewers' corrections to it, and write new
ones through the store (`app.store.clutter_corrections`, which checks them against the same
membership inside its write transaction).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from sqlmodel import Session

from app.core.errors import ConflictError
from app.pipelines.clutter.review_corrections import (
    ADD,
    REMOVE,
    MembershipCorrection,
    corrected_membership,
)
from app.store import clutter_corrections, clutter_review
from app.store.clutter_corrections import Corrected, RunMembership

__all__ = [
    "ADD",
    "REMOVE",
    "Corrected",
    "MembershipCorrection",
    "RunMembership",
    "add_object",
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
