"""The retraining trigger: every `settings.retrain_every` newly reviewed pillar labels (human
labels written since the last phantom training job was queued) queue one `train:phantom` job,
unless one is already waiting or running."""

from __future__ import annotations

import threading
from dataclasses import dataclass

from sqlalchemy.engine import Engine
from sqlmodel import Session, select

from app.core.settings import Settings
from app.jobs.queue import enqueue
from app.store.models import Job, JobStatus
from app.store.pillar_labels import human_labels_since

TRAIN_PHANTOM = "train:phantom"


@dataclass(frozen=True)
class RetrainingState:
    threshold: int  # 0: automatic retraining is off
    new_labels: int  # human labels written since the last training job was queued
    pending_job_id: int | None  # a queued or running training job


def retraining_state(session: Session, settings: Settings) -> RetrainingState:
    last = session.exec(
        select(Job).where(Job.kind == TRAIN_PHANTOM).order_by(Job.created_at.desc())
    ).first()
    pending = session.exec(
        select(Job).where(
            Job.kind == TRAIN_PHANTOM, Job.status.in_([JobStatus.queued, JobStatus.running])
        )
    ).first()
    since = None if last is None else last.created_at
    return RetrainingState(
        threshold=settings.retrain_every,
        new_labels=human_labels_since(session, since),
        pending_job_id=None if pending is None else pending.id,
    )


def maybe_queue_retraining(session: Session, settings: Settings) -> Job | None:
    """Queue `train:phantom` when enough new labels came in; returns the job it queued."""
    state = retraining_state(session, settings)
    if not state.threshold or state.pending_job_id is not None:
        return None
    if state.new_labels < state.threshold:
        return None
    return enqueue(session, TRAIN_PHANTOM, {"trigger": "labels"}, None, None, settings)


class RetrainingTrigger:
    """Checks the trigger after label writes, off the request path (FastAPI background task),
    one check at a time so two writes finishing together cannot queue two jobs."""

    def __init__(self, engine: Engine, settings: Settings):
        self.engine, self.settings = engine, settings
        self._lock = threading.Lock()

    def __call__(self) -> Job | None:
        if not self.settings.retrain_every:
            return None
        with self._lock, Session(self.engine) as session:
            return maybe_queue_retraining(session, self.settings)
