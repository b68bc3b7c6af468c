"""One connected browser tab: its user, its survey, its own scene and GUI, its current mode.

viser gives every client its own `client.scene` and `client.gui`, so two operators on the same
survey never see each other's selection or tool state, only each other's labels and decisions
(through the store and the label feed, which also reports the review writes the open mode
follows: `review_changed`). Everything a session does runs on its own worker thread, one call
at a time: viser's callbacks and the label feed only queue work here, so a slow store write
never stalls viser's event loop and a mode never needs a lock.

Label writes go through `app.store.pillar_labels` (the same versioned, undoable batches the REST
API writes) with a fresh database session per action, attributed to the session's user.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlmodel import Session
from viser import CameraHandle, ClientHandle, SceneClickEvent, SceneRectSelectEvent

from app.core.errors import (
    MmscleanError,
    NotFoundError,
    PermissionDeniedError,
)
from app.store import pillar_labels
from app.store.models import Role, User
from app.store.surveys import list_surveys, survey_trajectory
from app.store.users import has_role
from app.store.work_areas import get_area
from app.viewer.drive import DriveControls
from app.viewer.modes import MODES
from app.viewer.modes.base import Mode
from app.viewer.tickets import Ticket
from app.viewer.view_presets import HOTKEYS, PRESETS, heading_at, preset_offset

if TYPE_CHECKING:
    from app.viewer.server import ViewerServer
    from app.viewer.survey_view import SurveyView

log = logging.getLogger(__name__)
timing_log = logging.getLogger("app.viewer.timing")  # interactions answered slowly

CAMERA_OFFSET = np.array([-0.3, -0.4, 1.0])  # initial view: from above, a little behind-left
CAMERA_DISTANCE = (20.0, 150.0)  # metres, clamped from the map's size


class ViewerSession:
    def __init__(self, viewer: ViewerServer, client: ClientHandle, ticket: Ticket):
        self.viewer = viewer
        self.client = client
        self.user_id = ticket.user_id
        self.username = ticket.username
        self.requested_survey = ticket.survey_id
        self.requested_mode = ticket.mode
        self.requested_area = ticket.area_id  # looked at once, when its survey first opens
        self.view: SurveyView | None = None
        self.mode: Mode | None = None
        self.mode_folder: Any = None
        self.drive: DriveControls | None = None
        self.closed = False
        self._executor = ThreadPoolExecutor(1, thread_name_prefix=f"viewer-{client.client_id}")
        self._camera_pending = threading.Event()
        self._answered_at: float | None = None  # when the work in hand sent its answer
        self._gui: list[Any] = []
        self._survey_ids: dict[str, int] = {}
        self._hold_camera = False
        self.trajectory = np.zeros((0, 3))  # the open survey's drive, local coordinates

    # --- running work ----------------------------------------------------------------------

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future | None:
        """Run fn(*args) on this session's worker thread; errors become a notification."""
        if self.closed:
            return None
        try:
            return self._executor.submit(self._timed, time.perf_counter(), fn, *args)
        except RuntimeError:  # shut down meanwhile
            return None

    def _timed(self, received: float, fn: Callable[..., Any], *args: Any) -> Any:
        """Run fn and log how long the server took to answer it, from the moment the message
        arrived (`submit`) to its answer: the colours of a label write (`answered`), else the
        end of the work. Logged when slower than the `viewer_log_slower_ms` setting."""
        self._answered_at = None
        started = time.perf_counter()
        try:
            return self._guarded(fn, *args)
        finally:
            answered = self._answered_at or time.perf_counter()
            ms = 1000.0 * (answered - received)
            if ms >= self.viewer.settings.viewer_log_slower_ms:
                timing_log.warning(
                    "viewer client %s: %s answered in %.0f ms (%.0f ms of it waiting for "
                    "earlier work)", self.client.client_id, getattr(fn, "__name__", fn), ms,
                    1000.0 * (started - received),
                )  # fmt: skip

    def answered(self) -> None:
        """The work in hand has sent its answer (its first one counts)."""
        if self._answered_at is None:
            self._answered_at = time.perf_counter()

    def _guarded(self, fn: Callable[..., Any], *args: Any) -> Any:
        if self.closed:
            return None
        try:
            return fn(*args)
        except MmscleanError as exc:
            self.notify("Not done", exc.message, error=True)
        except Exception as exc:
            log.exception("viewer client %s: %s failed", self.client.client_id, fn)
            self.notify("Error", f"{type(exc).__name__}: {exc}", error=True)
        return None

    def notify(self, title: str, body: str, error: bool = False) -> None:
        if self.closed:
            return
        try:
            self.client.add_notification(
                title, body, auto_close_seconds=6.0, color="red" if error else None
            )
        except Exception:  # the client went away meanwhile
            log.debug("viewer client %s: notification dropped", self.client.client_id)

    def db(self) -> Session:
        return Session(self.viewer.engine, expire_on_commit=False)

    # --- lifecycle --------------------------------------------------------------------------

    def start(self) -> None:
        self.submit(self._start)

    def _start(self) -> None:
        gui = self.client.gui
        with self.db() as session:
            surveys = list_surveys(session)
        self._survey_ids = {f"{s.id}: {s.name}": int(s.id) for s in surveys}
        self._gui.append(gui.add_markdown(f"Logged in as **{self.username}**"))
        if not surveys:
            self._gui.append(gui.add_markdown("No survey yet: import one from the dashboard."))
            return
        survey_id = self.requested_survey or int(surveys[0].id)
        if survey_id not in self._survey_ids.values():
            raise NotFoundError(f"survey {survey_id} not found")
        label_of = {v: k for k, v in self._survey_ids.items()}
        survey_menu = gui.add_dropdown(
            "Survey", tuple(self._survey_ids), initial_value=label_of[survey_id]
        )
        first = next((m.name for m in MODES if m.key == self.requested_mode), MODES[0].name)
        mode_menu = gui.add_dropdown("Mode", tuple(m.name for m in MODES), initial_value=first)
        views = gui.add_button_group("View", PRESETS)
        self._gui += [survey_menu, mode_menu, views]
        views.on_click(lambda event: self.submit(self.show_preset, event.target.value))
        for preset, key in HOTKEYS.items():
            command = gui.add_command(f"View: {preset.lower()}", hotkey=key)
            command.on_trigger(lambda _, p=preset: self.submit(self.show_preset, p))
            self._gui.append(command)

        @survey_menu.on_update
        def _(_: Any) -> None:
            self.submit(self.open_survey, self._survey_ids[survey_menu.value])

        @mode_menu.on_update
        def _(_: Any) -> None:
            self.submit(self.switch_mode, mode_menu.value)

        self.client.scene.set_up_direction("+z")
        self.client.scene.on_click()(lambda event: self.submit(self._click, event))
        self.client.scene.on_rect_select(modifier="shift")(
            lambda event: self.submit(self._rect_select, event)
        )
        self.client.camera.on_update(self._camera_moved)
        self.open_survey(survey_id, mode_name=mode_menu.value)

    def open_survey(self, survey_id: int, mode_name: str | None = None) -> None:
        """Show another survey (or the first one): the current mode is rebuilt on it."""
        mode_name = mode_name or (self.mode.name if self.mode else MODES[0].name)
        if self.view is not None and self.view.survey_id == survey_id:
            return
        self._leave_mode()
        self._remove_drive()
        if self.view is not None:
            self.view.unsubscribe(self._labels_changed)
            self.viewer.views.release(self.view)
            self.view = None
        loading = self.client.add_notification(
            "Loading", "Opening the survey's map...", loading=True, with_close_button=False
        )
        try:
            self.view = self.viewer.views.acquire(survey_id)
        finally:
            loading.remove()
        self.view.subscribe(self._labels_changed)
        self._place_camera()
        if self.requested_area is not None and survey_id == self.requested_survey:
            self._look_at_area(self.requested_area)
            self.requested_area = None
        self._add_drive()
        self.switch_mode(mode_name)

    def _add_drive(self) -> None:
        """The "Drive" controls of the open survey (`drive.py`), where it has a drive."""
        survey_map = self.view.map
        with self.db() as session:
            trajectory = survey_trajectory(session, self.view.survey_id) - survey_map.origin
        self.trajectory = trajectory
        self.drive = DriveControls.maybe(
            self.client.gui, trajectory,
            lambda xy: float(survey_map.ground.height(xy[None])[0]) if len(survey_map) else 0.0,
            self.move_camera, self.submit,
        )  # fmt: skip

    def _remove_drive(self) -> None:
        if self.drive is not None:
            self.drive.remove()
            self.drive = None

    def _place_camera(self) -> None:
        """Look down at the middle of the map, a little from behind-left: at the overview's
        point nearest the middle of its bounds (the middle of a long winding drive's bounds
        may hold no point, and the tile in focus there none)."""
        survey_map = self.view.map
        lo, hi = survey_map.bounds()
        centre = (lo[:2].astype(np.float64) + hi[:2]) / 2.0
        if len(survey_map.overview):
            xy = np.asarray(survey_map.xyz[survey_map.overview, :2], dtype=np.float64)
            centre = xy[int(np.argmin(((xy - centre) ** 2).sum(axis=1)))]
        self._look_down_at(centre, float(np.max(hi[:2] - lo[:2])))

    def _look_down_at(self, centre: np.ndarray, extent: float) -> None:
        """Look at the ground under local `centre` (x, y) from above, a little behind-left,
        from a distance that shows `extent` metres."""
        survey_map = self.view.map
        ground = float(survey_map.ground.height(centre[None])[0]) if len(survey_map) else 0.0
        distance = float(np.clip(0.9 * extent, *CAMERA_DISTANCE))
        offset = CAMERA_OFFSET / np.linalg.norm(CAMERA_OFFSET) * distance
        self.move_camera(np.array([centre[0], centre[1], ground]), offset)

    def _look_at_area(self, area_id: int) -> None:
        """Look down at a work area (a dashboard's link): its pillars' box whole in view."""
        with self.db() as session:
            try:
                area = get_area(session, self.view.survey_id, area_id)
            except NotFoundError as exc:
                self.notify("Work area", f"{exc.message}: showing the whole survey.", error=True)
                return
        origin = self.view.map.origin[:2]
        lo = np.array([area.x_min, area.y_min]) - origin
        hi = np.array([area.x_max, area.y_max]) - origin
        self._look_down_at((lo + hi) / 2.0, float(np.max(hi - lo)))
        self.notify(
            f"Work area {area.area_index}",
            f"{area.station_start:.0f}-{area.station_end:.0f} m along the drive, "
            f"{area.state.value.replace('_', ' ')}.",
        )

    def move_camera(self, look_at: np.ndarray, offset: np.ndarray) -> None:
        if self._hold_camera:  # a mode reloading itself: the user's view stays
            return
        camera = self.client.camera
        camera.up_direction = (0.0, 0.0, 1.0)
        camera.position = look_at + offset  # moves look_at along ...
        camera.look_at = look_at  # ... so set it after the position

    def show_preset(self, preset: str) -> None:
        """Swing the camera to a standard view (`view_presets`) of the point it looks at."""
        camera = self.client.camera
        look_at = np.asarray(camera.look_at, dtype=np.float64)
        distance = float(np.linalg.norm(np.asarray(camera.position) - look_at))
        heading = heading_at(self.trajectory, look_at[:2])
        self.move_camera(look_at, preset_offset(preset, heading, distance))

    def switch_mode(self, name: str) -> None:
        if self.mode is not None and self.mode.name == name:
            return
        self._leave_mode()
        if self.view is None:
            return
        mode_class = next(m for m in MODES if m.name == name)
        self.mode_folder = self.client.gui.add_folder(name)
        self.mode = mode_class()
        self.mode.enter(self)
        self.client.flush()

    def reload_mode(self) -> Mode | None:
        """Leave the open mode and enter a fresh one of the same kind (a new pipeline run or
        rebuild replaced what it shows), keeping the camera where the user put it; the new mode."""
        if self.mode is None or self.view is None:
            return None
        mode_class = type(self.mode)
        self._leave_mode()
        self.mode_folder = self.client.gui.add_folder(mode_class.name)
        self.mode = mode_class()
        self._hold_camera = True
        try:
            self.mode.enter(self)
        finally:
            self._hold_camera = False
        self.trajectory = np.zeros((0, 3))  # the open survey's drive, local coordinates
        self.client.flush()
        return self.mode

    def _leave_mode(self) -> None:
        if self.mode is not None:
            try:
                self.mode.leave()
            finally:
                self.mode = None
                if self.mode_folder is not None:
                    self.mode_folder.remove()
                    self.mode_folder = None

    def close(self) -> None:
        """The client disconnected: leave the mode and give the survey back (off its thread)."""
        self._executor.submit(self._close)
        self._executor.shutdown(wait=False)

    def _close(self) -> None:
        self.closed = True
        try:
            self._leave_mode()
        except Exception:  # the client's scene is gone; only our bookkeeping matters now
            log.debug("viewer client %s: leave after disconnect failed", self.client.client_id)
        self.mode = None
        if self.view is not None:
            self.view.unsubscribe(self._labels_changed)
            self.viewer.views.release(self.view)
            self.view = None

    # --- events routed to the mode ------------------------------------------------------------

    def _click(self, event: SceneClickEvent) -> None:
        if self.mode is not None:
            self.mode.on_click(event)

    def _rect_select(self, event: SceneRectSelectEvent) -> None:
        if self.mode is not None:
            self.mode.on_rect_select(event)

    def _camera_moved(self, camera: CameraHandle) -> None:
        """Viser's pool thread, many times a second while orbiting: queue at most one call."""
        if not self._camera_pending.is_set():
            self._camera_pending.set()
            self.submit(self._camera_settled, camera)

    def _camera_settled(self, camera: CameraHandle) -> None:
        self._camera_pending.clear()
        if self.mode is not None:
            self.mode.on_camera(camera)

    def _labels_changed(self, changed: np.ndarray) -> None:
        """From the label feed's thread: recolour on ours."""
        self.submit(self._recolor, changed)

    def _recolor(self, changed: np.ndarray) -> None:
        if self.mode is not None:
            self.mode.on_labels_changed(changed)
            self.client.flush()

    def review_changed(self, survey_id: int, actions: frozenset[str]) -> None:
        """From the label feed's thread: review writes on a survey (anyone's, ours included);
        the open mode follows them on our thread."""
        self.submit(self._review_changed, survey_id, actions)

    def _review_changed(self, survey_id: int, actions: frozenset[str]) -> None:
        if self.mode is not None and self.view is not None and self.view.survey_id == survey_id:
            self.mode.on_review_changed(set(actions))
            self.client.flush()

    # --- label writes (the store's batches, attributed to this user) ---------------------------

    def _check_user(self, session: Session) -> None:
        user = session.get(User, self.user_id)
        if user is None or not user.is_active:
            raise PermissionDeniedError(f"user {self.username!r} is no longer active")
        if not has_role(user, Role.annotator):
            raise PermissionDeniedError(f"user {self.username!r} may not label")

    def write_pillar_labels(
        self, cell_ids: np.ndarray, labels: np.ndarray
    ) -> pillar_labels.LabelWrite:
        """One labelling action (store cell ids; NO_LABEL erases) as one undoable batch,
        checked against the label versions the view shows: a pillar someone else labelled
        since raises `StaleWriteError`, nothing is written and the view shows their label.
        The new colours go out before the store's write (tens of thousands of pillars take
        SQLite half a second); a refused or failed write puts the store's labels back."""
        view = self.view
        expected = view.human_versions(cell_ids)
        shown = view.show_labels(cell_ids, labels)
        if len(shown) and self.mode is not None:
            self.mode.on_labels_changed(shown)
            self.client.flush()
            self.answered()
        try:
            with self.db() as session:
                self._check_user(session)
                result = pillar_labels.write_labels(
                    session, view.survey_id, self.user_id, cell_ids, labels, expected
                )
        except BaseException:
            view.refresh_human(np.asarray(cell_ids, dtype=np.int64))  # the store's, announced
            raise
        changed = view.take_written(
            result.cell_ids, labels, result.versions, shown, self._labels_changed
        )
        if len(changed) and self.mode is not None:
            self.mode.on_labels_changed(changed)
        self.viewer.labels_written()
        return result

    def undo_pillars(self) -> pillar_labels.LabelWrite:
        with self.db() as session:
            self._check_user(session)
            result = pillar_labels.undo(session, self.view.survey_id, self.user_id)
        return self._written(result)

    def redo_pillars(self) -> pillar_labels.LabelWrite:
        with self.db() as session:
            self._check_user(session)
            result = pillar_labels.redo(session, self.view.survey_id, self.user_id)
        return self._written(result)

    def _written(self, result: pillar_labels.LabelWrite) -> pillar_labels.LabelWrite:
        """The view takes our write (and its versions) at once, before our next action can
        be checked against it; the label feed then tells the other clients and views."""
        self.view.refresh_human(result.cell_ids)
        self.viewer.labels_written()
        return result
