"""The retraining trigger: every `settings.retrain_every` newly reviewed pillar labels (human
labels written since the last phantom training job was queued, whatever became of it) queue one
`train:phantom` job, unless one is already waiting or running, or the labels could not train
it: the task's own prerequisites (`app.jobs.phantom_training_data`) are checked first, and what
blocks training is reported (`blocked_by`, in GET /models/retraining) instead of queueing a job
bound to fail. The count people see (`new_labels`) runs from the last training that succeeded:
a failed one used no label.

`readiness`: per trainable pipeline, what keeps an on-demand retraining from training now (the
tasks' own checks on the labels as they are) and how its last training job ended, so the
dashboard offers the button only when it can work and shows a failure where it was started."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.core.errors import ConfigError, MmscleanError
from app.core.settings import Settings
from app.jobs.phantom_training_data import label_counts, training_blocker
from app.jobs.queue import enqueue
from app.jobs.training_tasks import (
    GuardrailRetrainConfig,
    PhantomRetrainConfig,
    guardrail_training_slices,
    phantom_training_labels,
)
from app.store.jobs import newest_job_of_kind, pending_job_of_kind
from app.store.models import Job, JobStatus
from app.store.pillar_reads import human_labels_since
from app.store.training_labels import human_pillar_labels

TRAIN_PHANTOM = "train:phantom"
TRIGGER_CONFIG = {"trigger": "labels"}

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RetrainingState:
    threshold: int  # 0: automatic retraining is off
    new_labels: int  # human labels written since the last training job that succeeded
    pending_job_id: int | None  # a queued or running training job
    blocked_by: str | None = None  # why the due retraining is not queued (checked when due)
    # since the last training job queued, whatever became of it: the trigger counts these, so a
    # job that failed for another reason (memory, a lost worker) is not queued again at once
    since_last_job: int = 0

    @property
    def due(self) -> bool:
        return (
            bool(self.threshold)
            and self.pending_job_id is None
            and (self.since_last_job >= self.threshold)
        )


def retraining_state(session: Session, settings: Settings) -> RetrainingState:
    succeeded = newest_job_of_kind(session, TRAIN_PHANTOM, JobStatus.succeeded)
    last = newest_job_of_kind(session, TRAIN_PHANTOM)
    pending = pending_job_of_kind(session, TRAIN_PHANTOM)
    state = RetrainingState(
        threshold=settings.retrain_every,
        new_labels=human_labels_since(session, None if succeeded is None else succeeded.created_at),
        pending_job_id=None if pending is None else pending.id,
        since_last_job=human_labels_since(session, None if last is None else last.created_at),
    )
    if state.due:
        state = RetrainingState(**{**state.__dict__, "blocked_by": training_blocked_by(session)})
    return state


@dataclass(frozen=True)
class Readiness:
    """An on-demand retraining of one pipeline: what keeps it from training (None: ready) and
    its newest training job."""

    pipeline: str
    blocked_by: str | None
    last_job: Job | None


TRAINING = {
    "phantom": (TRAIN_PHANTOM, PhantomRetrainConfig, phantom_training_labels),
    "guardrail": ("train:guardrail", GuardrailRetrainConfig, guardrail_training_slices),
}


def readiness(session: Session, pipeline: str, config: dict | None = None) -> Readiness:
    """The task's own checks on the labels now (`config`: the job's, default all surveys)."""
    kind, model, gather = TRAINING[pipeline]
    try:
        gather(session, model(**(config or {})))
        blocked = None
    except ConfigError as exc:  # "labels: 3 human pillar labels; ..." reads as the labels'
        blocked = exc.message.removeprefix("labels: ") if exc.field == "labels" else exc.message
    except MmscleanError as exc:  # e.g. a labelled survey whose files are gone
        blocked = exc.message
    return Readiness(pipeline, blocked, newest_job_of_kind(session, kind))


def training_blocked_by(session: Session) -> str | None:
    """Why the job the trigger would queue could not train, from the labels on pillars a
    phantom run found points in (its model pre-labels; labels elsewhere count for nothing)."""
    cfg = PhantomRetrainConfig(**TRIGGER_CONFIG)
    labels = human_pillar_labels(session, cfg.survey_ids, with_mapped=True)
    return training_blocker(label_counts(labels, cfg, with_points=True), cfg)


def maybe_queue_retraining(session: Session, settings: Settings) -> Job | None:
    """Queue `train:phantom` when enough new labels came in and they can train it; returns the
    job it queued."""
    state = retraining_state(session, settings)
    if not state.due:
        return None
    if state.blocked_by is not None:
        log.info("retraining due but not queued: %s", state.blocked_by)
        return None
    try:
        return enqueue(session, TRAIN_PHANTOM, dict(TRIGGER_CONFIG), None, None, settings)
    except MmscleanError as exc:  # e.g. over MMSCLEAN_JOB_MEMORY_MB: said, not raised, since
        session.rollback()  # the trigger runs after a label write's answer was sent
        log.warning("retraining due but not queued: %s", exc.message)
        return None


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
