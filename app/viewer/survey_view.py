"""One open survey, shared by every viewer client looking at it: its map and the current label
of each of its pillars, kept in step with the store.

Labels are read from the store once when the first client opens the survey, then patched: the
label feed reports which pillars changed (whoever changed them: this viewer, the REST API, a
job, another process) and the view re-reads just those and tells its listeners which pillars
now look different, so each client resends colours, never positions.

The view also keeps the version of each human label it shows: a client's label write passes
them as the versions it saw, so a label someone else wrote after this view last read it is
never overwritten unseen (the store refuses the batch and the view re-reads those pillars).

A client's own write is shown before the store has it (`show_labels`: the writer's colours go
out while SQLite writes, a large batch's half second), its versions unchanged until the write
is done (`take_written`, which tells the other listeners); a refused or failed write puts the
store's labels back (`refresh_human`).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.review.survey_map import MapSource, SurveyMap, load_map
from app.store.label_arrays import SurveyLabelArrays, survey_label_arrays
from app.store.pillar_labels import human_columns
from app.store.surveys import get_survey
from app.viewer.pillar_colors import display_class, pillar_colors

log = logging.getLogger(__name__)

Listener = Callable[[np.ndarray], None]  # gets the indices (into map.cells) that changed


class SurveyView:
    def __init__(self, engine: Engine, survey_id: int, name: str, survey_map: SurveyMap):
        self.engine = engine
        self.survey_id = survey_id
        self.name = name
        self.map = survey_map
        m = len(survey_map.cells)
        self.human = np.full(m, -1, dtype=np.int8)
        self.version = np.zeros(m, dtype=np.int64)  # of the human label shown (or its erase)
        self.model = np.full(m, -1, dtype=np.int8)
        self.confidence = np.full(m, np.nan, dtype=np.float32)
        self.rgb = pillar_colors(self.human, self.model, self.confidence)
        self.klass = display_class(self.human, self.model)
        self.lock = threading.Lock()  # guards the label arrays; held briefly
        # One re-read at a time (the label feed's and a client's own), so an older read can
        # never be applied after a newer one.
        self._reading = threading.Lock()
        self._listeners: list[Listener] = []

    # --- listeners ---------------------------------------------------------------------------

    def subscribe(self, listener: Listener) -> None:
        with self.lock:
            self._listeners.append(listener)

    def unsubscribe(self, listener: Listener) -> None:
        with self.lock:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def _announce(self, changed: np.ndarray, skip: Listener | None = None) -> None:
        if not len(changed):
            return
        with self.lock:
            listeners = tuple(x for x in self._listeners if x != skip)
        for listener in listeners:
            try:
                listener(changed)
            except Exception:
                log.exception("viewer listener failed on survey %s", self.survey_id)

    # --- reading the store -------------------------------------------------------------------

    def load_all(self) -> np.ndarray:
        """Re-read every label of the survey; returns the pillars whose colour changed."""
        with self._reading:
            with Session(self.engine) as session:
                labels = survey_label_arrays(session, self.survey_id)
            changed = self._set_all(labels)
        self._announce(changed)
        return changed

    def _set_all(self, stored: SurveyLabelArrays) -> np.ndarray:
        is_human, labels, confidence = stored.is_human, stored.labels, stored.confidence
        versions = stored.versions
        k, found = self.map.cell_index(stored.cell_ids)
        human = np.full(len(self.map.cells), -1, dtype=np.int8)
        version = np.zeros(len(self.map.cells), dtype=np.int64)
        model = np.full(len(self.map.cells), -1, dtype=np.int8)
        conf = np.full(len(self.map.cells), np.nan, dtype=np.float32)
        h, m = found & is_human, found & ~is_human
        human[k[h]] = labels[h]
        version[k[h]] = versions[h]
        model[k[m]] = labels[m]
        conf[k[m]] = confidence[m]
        with self.lock:
            self.human, self.version, self.model, self.confidence = human, version, model, conf
            return self._recolor(np.arange(len(self.map.cells)))

    def refresh_human(self, cell_ids: np.ndarray) -> np.ndarray:
        """Re-read the human labels of these pillars (store cell ids); returns those that now
        look different (already announced)."""
        k, found = self.map.cell_index(cell_ids)
        k = np.unique(k[found])
        if not len(k):
            return k
        with self._reading:
            with Session(self.engine) as session:
                labels, versions = human_columns(session, self.survey_id, self.map.cells[k])
            with self.lock:
                self.human[k] = labels
                self.version[k] = versions
                changed = self._recolor(k)
        self._announce(changed)
        return changed

    def show_labels(self, cell_ids: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Show the human labels a client is writing (store cell ids; NO_LABEL (-1) erases)
        before the store has them, versions unchanged; returns the pillars that now look
        different, told to no listener yet (`take_written` does, or `refresh_human` puts the
        store's labels back)."""
        k, found = self.map.cell_index(np.asarray(cell_ids, dtype=np.int64))
        with self.lock:
            self.human[k[found]] = np.asarray(labels, dtype=np.int64)[found]
            return self._recolor(k[found])

    def take_written(
        self, cell_ids: np.ndarray, labels: np.ndarray, versions: np.ndarray,
        shown: np.ndarray, writer: Listener,
    ) -> np.ndarray:  # fmt: skip
        """A client's write is in the store: its labels and their new versions (request order)
        are the view's; the pillars `show_labels` changed (`shown`) and any that change now
        are told to every listener but the writer's. Returns those that changed now."""
        k, found = self.map.cell_index(np.asarray(cell_ids, dtype=np.int64))
        with self.lock:
            self.human[k[found]] = np.asarray(labels, dtype=np.int64)[found]
            self.version[k[found]] = np.asarray(versions, dtype=np.int64)[found]
            changed = self._recolor(k[found])
        self._announce(np.union1d(shown, changed), skip=writer)
        return changed

    def human_versions(self, cell_ids: np.ndarray) -> list[int | None]:
        """The versions of the human labels shown on these pillars (store cell ids; 0: never
        labelled; an erased one: its erase's): what a client of this view saw before its
        write. None for a pillar without points, which the view does not show (nothing seen,
        nothing to check)."""
        k, found = self.map.cell_index(cell_ids)
        versions = np.full(len(found), None, dtype=object)
        with self.lock:
            versions[found] = self.version[k[found]].tolist()
        return versions.tolist()

    def _recolor(self, k: np.ndarray) -> np.ndarray:
        """Recompute the colour and class of pillars k (lock held); the ones that changed."""
        rgb = pillar_colors(self.human[k], self.model[k], self.confidence[k])
        klass = display_class(self.human[k], self.model[k])
        changed = (rgb != self.rgb[k]).any(axis=1) | (klass != self.klass[k])
        self.rgb[k] = rgb
        self.klass[k] = klass
        return k[changed]

    # --- what clients read ---------------------------------------------------------------------

    def point_colors(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) uint8 colours of map points `points`."""
        return self.pillar_rgb(self.map.cell[points])

    def pillar_rgb(self, k: np.ndarray) -> np.ndarray:
        """(n, 3) uint8 colours of pillars `cells[k]` (a shown point's pillar, repeated)."""
        with self.lock:
            return self.rgb[k]

    def pillar_confidence(self, k: np.ndarray) -> np.ndarray:
        """(n,) float32 model confidence of pillars `cells[k]` (NaN: no model pre-label)."""
        with self.lock:
            return np.where(self.model[k] >= 0, self.confidence[k], np.nan)

    def pillar_state(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(human label (-1: none), display class) of pillars `cells[k]`."""
        with self.lock:
            return self.human[k].astype(np.int64), self.klass[k].astype(np.int64)

    def pillar_labels(self, k: int) -> tuple[int, int, float]:
        """(human label, model label (-1: none), model confidence) of pillar `cells[k]`."""
        with self.lock:
            return int(self.human[k]), int(self.model[k]), float(self.confidence[k])

    def point_classes(self, points: np.ndarray) -> np.ndarray:
        cells = self.map.cell[points]
        with self.lock:
            return self.klass[cells]


class SurveyViews:
    """Open surveys by id, loaded once and shared; dropped when their last client leaves."""

    def __init__(self, engine: Engine, cache_dir: Path, overview_points: int):
        self.engine = engine
        self.cache_dir = cache_dir
        self.overview_points = overview_points
        self._views: dict[int, SurveyView] = {}
        self._users: dict[int, int] = {}
        self._loading: dict[int, threading.Lock] = {}
        self._lock = threading.Lock()

    def acquire(self, survey_id: int) -> SurveyView:
        """The view of a survey (loading its map and labels when nobody has it open)."""
        with self._lock:
            gate = self._loading.setdefault(survey_id, threading.Lock())
        with gate:  # one load per survey, however many clients open it at once
            with self._lock:
                view = self._views.get(survey_id)
                if view is not None:
                    self._users[survey_id] += 1
                    return view
            view = self._open(survey_id)
            with self._lock:  # registered first, so the feed reports changes from now on
                self._views[survey_id] = view
                self._users[survey_id] = 1
            try:
                view.load_all()
            except BaseException:
                self.release(view)
                raise
            return view

    def release(self, view: SurveyView) -> None:
        with self._lock:
            left = self._users.get(view.survey_id, 0) - 1
            if left > 0:
                self._users[view.survey_id] = left
                return
            self._users.pop(view.survey_id, None)
            self._views.pop(view.survey_id, None)

    def get(self, survey_id: int) -> SurveyView | None:
        with self._lock:
            return self._views.get(survey_id)

    def open_ids(self) -> list[int]:
        with self._lock:
            return list(self._views)

    def _open(self, survey_id: int) -> SurveyView:
        with Session(self.engine) as session:
            record = get_survey(session, survey_id)
            source = MapSource.of(record)
            name = record.name
        survey_map = load_map(source, self.cache_dir, self.overview_points)
        return SurveyView(self.engine, survey_id, name, survey_map)
