"""The viewer's mode interface: one annotation task (pillar labelling, clutter review, guardrail
review, model inspection, QA) = one `Mode` subclass in its own module of `app/viewer/modes/`,
listed in `app.viewer.modes.MODES`; the session shows the modes in its "Mode" dropdown.

How the session drives a mode:

- `enter(session)` when the user picks the mode (and when the survey changes): build the scene
  nodes and the GUI. GUI elements go inside `with session.mode_folder:` (the session removes the
  folder after `leave`); scene nodes go under `/<key>/...` of `session.client.scene`; hotkeys
  are `session.client.gui.add_command(...)` handles the mode removes itself in `leave`.
- `leave()` when the user picks another mode, the survey changes or the client disconnects:
  remove every scene node and command the mode added.
- `on_click(event)`: a plain left click in the canvas (`SceneClickEvent`: ray origin and
  direction in the scene's local coordinates, screen position).
- `on_rect_select(event)`: a shift-drag rectangle (`SceneRectSelectEvent`: screen corners in
  0..1; project points with `event.client.camera`, see `app.viewer.picking`).
- `on_camera(camera)`: the client's camera moved (at most one pending call: later moves
  coalesce into one call with the newest camera).
- `on_labels_changed(changed)`: pillar labels of the open survey changed (by anyone): `changed`
  indexes `session.view.map.cells`; recolour with `session.view.point_colors` (or
  `pillar_rgb` of the pillars of points already gathered, `app.viewer.shown_points`).
- `on_review_changed(actions)`: review writes on the open survey (by anyone, this user's own
  included, so applying one must be idempotent): `actions` is the set of audit actions seen
  since the last call (`app.viewer.label_feed.REVIEW_ACTIONS`: clutter decisions and runs,
  guardrail slice labels, model decisions, runs and rebuilds; `job.succeeded:<kind>` for each
  finished job). Re-read what the mode shows
  and recolour, keeping the user's selection; after a new run or a rebuild a mode may call
  `session.reload_mode()` (leave, then enter a fresh mode of its kind; the camera stays).

Every call above runs on the session's own worker thread, one at a time, so a mode keeps plain
attributes without locks. GUI callbacks fire on viser's thread pool instead: forward them with
`session.submit(fn, *args)`. Label writes go through `session.write_pillar_labels`,
`session.undo_pillars` and `session.redo_pillars` (the store's versioned batches, attributed to
the session's user); store errors raised inside a mode call become a notification.
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, ClassVar

import numpy as np

if TYPE_CHECKING:
    from viser import CameraHandle, SceneClickEvent, SceneRectSelectEvent

    from app.viewer.session import ViewerSession


class Mode(abc.ABC):
    name: ClassVar[str]  # shown in the mode dropdown
    key: ClassVar[str]  # scene node prefix, e.g. "pillars"

    def __init__(self) -> None:
        self.session: ViewerSession | None = None

    @abc.abstractmethod
    def enter(self, session: ViewerSession) -> None:
        """Build this mode's scene and GUI for `session`."""

    @abc.abstractmethod
    def leave(self) -> None:
        """Remove everything `enter` added (the session removes the mode folder)."""

    def on_click(self, event: SceneClickEvent) -> None:
        """A plain left click in the canvas."""
        return None  # optional: modes override what they use

    def on_rect_select(self, event: SceneRectSelectEvent) -> None:
        """A shift-drag rectangle in the canvas."""
        return None  # optional: modes override what they use

    def on_camera(self, camera: CameraHandle) -> None:
        """The client's camera moved."""
        return None  # optional: modes override what they use

    def on_labels_changed(self, changed: np.ndarray) -> None:
        """Pillar labels of the open survey changed (indices into `session.view.map.cells`)."""
        return None  # optional: modes override what they use

    def on_review_changed(self, actions: set[str]) -> None:
        """Review writes on the open survey (audit actions, see `label_feed.REVIEW_ACTIONS`)."""
        return None  # optional: modes override what they use
