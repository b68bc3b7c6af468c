"""Which pillar labels and review decisions changed, whoever changed them: a tail of the audit
log.

Every label write in the store leaves an audit row in the same transaction (`pillar.label`,
`pillar.undo`, `pillar.redo` name an edit batch, whose edits list the pillars;
`pillar.model_labels` names a survey whose model pre-labels a job replaced). Following the
audit log by id therefore sees writes from the REST API, from viewer clients, from job worker
processes and from other server processes alike, in commit order (SQLite has one writer at a
time, so ids are handed out in commit order), and costs one index range read per poll.

The same tail reports the review writes of the other modes per survey (`ReviewChange`: which
`REVIEW_ACTIONS` happened): clutter decisions (`clutter.approve` / `clutter.reject` /
`clutter.reset`, survey in the payload), corrections of clutter instances
(`clutter.remove_points`, `clutter.add_object`) and a new clutter run (`clutter.ingest`),
guardrail slice labels (`guardrail_slice.label`) and model decisions
(`guardrail_model.approve` / `.reject`), a new guardrail run (`guardrail.ingest`) and a
rebuild of its models (`guardrail.rebuild`), and finished jobs (`job.succeeded`, reported as
`job.succeeded:<kind>`: new results to show).

The feed polls every `interval` seconds; `wake()` makes it poll now, which the API calls after
a label or review write so open viewers recolour within milliseconds instead of at the next poll.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.store.audit_tail import batch_cells, events_after, newest_audit_id
from app.store.jobs import JOB_SUCCEEDED

log = logging.getLogger(__name__)

BATCH_ACTIONS = ("pillar.label", "pillar.undo", "pillar.redo")
MODEL_ACTION = "pillar.model_labels"
LABEL_ACTIONS = (*BATCH_ACTIONS, MODEL_ACTION)
CLUTTER_DECISIONS = frozenset({"clutter.approve", "clutter.reject", "clutter.reset"})
CLUTTER_CORRECTIONS = frozenset({"clutter.remove_points", "clutter.add_object"})
CLUTTER_RUN = "clutter.ingest"
SLICE_LABEL = "guardrail_slice.label"
MODEL_DECISIONS = frozenset({"guardrail_model.approve", "guardrail_model.reject"})
GUARDRAIL_RUN = frozenset({"guardrail.ingest", "guardrail.rebuild"})
REVIEW_ACTIONS = frozenset(
    {
        *CLUTTER_DECISIONS,
        *CLUTTER_CORRECTIONS,
        CLUTTER_RUN,
        SLICE_LABEL,
        *MODEL_DECISIONS,
        *GUARDRAIL_RUN,
    }
)

_ACTIONS = frozenset({*LABEL_ACTIONS, *REVIEW_ACTIONS, JOB_SUCCEEDED})


def job_succeeded(kind: str) -> str:
    """The review action a feed reports when a job of `kind` succeeded on a survey."""
    return f"{JOB_SUCCEEDED}:{kind}"


@dataclass
class LabelChange:
    survey_id: int
    human_cells: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    model_replaced: bool = False  # a job replaced the survey's model pre-labels


@dataclass
class ReviewChange:
    """Review writes on one survey since the last poll: which `REVIEW_ACTIONS` happened."""

    survey_id: int
    actions: set[str] = field(default_factory=set)


def read_changes(session: Session, after_id: int) -> tuple[int, list[LabelChange]]:
    """(newest audit id seen, label changes per survey) since audit id `after_id`."""
    last_id, labels, _ = read_events(session, after_id)
    return last_id, labels


def read_events(
    session: Session, after_id: int
) -> tuple[int, list[LabelChange], list[ReviewChange]]:
    """(newest audit id seen, label changes per survey, review changes per survey) since audit
    id `after_id`."""
    events = events_after(session, after_id, _ACTIONS)
    if not events:
        return after_id, [], []
    reviews: dict[int, ReviewChange] = {}
    for event in events:
        if event[3] is None:
            continue
        if event[1] in REVIEW_ACTIONS:
            action = event[1]
        elif event[1] == JOB_SUCCEEDED:
            action = job_succeeded(str(event[4]))
        else:
            continue
        reviews.setdefault(int(event[3]), ReviewChange(int(event[3]))).actions.add(action)
    changes: dict[int, LabelChange] = {}
    batches = [int(e[2]) for e in events if e[1] in BATCH_ACTIONS and e[2] is not None]
    if batches:
        for survey_id, cells in batch_cells(session, batches).items():
            changes[survey_id] = LabelChange(survey_id, np.unique(cells))
    for event in events:
        if event[1] == MODEL_ACTION and event[2] is not None:
            survey_id = int(event[2])
            changes.setdefault(survey_id, LabelChange(survey_id)).model_replaced = True
    return int(events[-1][0]), list(changes.values()), list(reviews.values())


class LabelFeed:
    """A thread that reports label changes to `on_changes` and review changes to `on_reviews`
    (when given), oldest first."""

    def __init__(
        self,
        engine: Engine,
        on_changes: Callable[[list[LabelChange]], None],
        interval: float = 0.5,
        on_reviews: Callable[[list[ReviewChange]], None] | None = None,
    ):
        self.engine = engine
        self.on_changes = on_changes
        self.on_reviews = on_reviews
        self.interval = interval
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.last_id = 0

    def start(self) -> LabelFeed:
        with Session(self.engine) as session:
            self.last_id = newest_audit_id(session)
        self._thread = threading.Thread(target=self._run, name="viewer-label-feed", daemon=True)
        self._thread.start()
        return self

    def wake(self) -> None:
        self._wake.set()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def poll(self) -> None:
        with Session(self.engine) as session:
            self.last_id, changes, reviews = read_events(session, self.last_id)
        if changes:
            self.on_changes(changes)
        if reviews and self.on_reviews is not None:
            self.on_reviews(reviews)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self.interval)
            self._wake.clear()
            if self._stop.is_set():
                break
            try:
                self.poll()
            except Exception:  # a locked or closing database: try again next tick
                log.exception("viewer label feed: poll failed")
