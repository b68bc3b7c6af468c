"""Clutter review: judge, frame by frame, the objects a clutter run removed.

A `run:clutter` job leaves per frame the membership of its review units (`instances/<frame>.npz`
in its folder: each point's instance and the pipeline's own removed flag) and one mask image per
instance; the store holds each instance's decision and version. This mode shows one frame at a
time: its LiDAR points re-centred on the survey origin and coloured by what the map will lose
with the current decisions applied (approved -> removed, rejected -> kept, pending -> the
pipeline's flag), the camera image with the instances' masks and points drawn over it, and the
instance list with approve / reject per instance and for every pending one of the frame.

Decisions go through `app.store.clutter_review.decide` (the API's own versioned batch, as this
session's user); a stale version means someone else decided first: the frame is re-read and the
reviewer told. "Recompute cleaned map" queues `clutter:recompute`. Decisions written by anyone
else (the API, another client) re-read the open frame's instances and recolour it, keeping the
selection; a new clutter run reloads the mode.

Camera and 3D together: "Panel width" (small / medium / large, the viser theme's control width
and the panel's own width, per client; medium when the mode is left) makes the camera image
beside the 3D view as large as the reviewer wants. Selecting an instance (a click on one of its
points, or *Select* in the list) draws it magenta in both views: its points in 3D, and on the
camera image its projected points, its mask outlined and its box. viser reports no hover events
to the server, but the browser outlines a clickable mesh under the pointer: each instance has an
invisible box round its points in 3D and, while the camera image is in the scene, a slab over
its box there (`clutter_hover`), so hovering an instance lights it up where the pointer is and a
click selects it in both views.

Correcting an instance's extent (reviewers), with a shift-drag rectangle in the 3D view (the
shown points inside it that the camera sees, depth-aware as the pillar mode's rectangle,
`pillar_selection.rectangle_points`): "Remove from instance" takes the selected instance's
points inside it out of the instance (they are kept, whatever its decision); "Add missed
object" makes the points inside it that belong to no instance a new instance of the chosen
class on this frame, approved. Both are versioned, audited store writes attributed to the user
(`app.review.clutter_corrections`, the API's too); other clients follow through the label feed
and `clutter:recompute` applies them.

The camera image in 3D (`clutter_camera`): "Camera image in 3D" draws the overlay image in the
scene on the rays its pixels see, and the view "Through the camera" looks from the camera's
optical centre, where each pixel covers the points it sees. A Ctrl-drag on that image is a 2D box
(CVAT's, SUSTechPOINTS'): "Add missed object" makes the object the camera sees most in the box a
new instance (`app.review.box_objects`: above the ground, the facade behind it left out), and
"Remove from instance" takes the selected instance's points in the box out of it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from app.core.errors import ConflictError, StaleWriteError
from app.geometry.projection import Projection, camera_pose, pixel_indices, project
from app.io import open_survey
from app.io.survey import Frame, Survey
from app.jobs.queue import enqueue
from app.review import clutter_corrections
from app.review.box_objects import PixelBox, object_in_box, run_camera, run_config
from app.review.clutter_corrections import RunMembership
from app.store import clutter_review
from app.store.clutter_corrections import OBJECT_CLASSES
from app.store.clutter_review import DecisionWrite, FrameCount, InstanceState
from app.store.models import Decision, Role
from app.store.models import Survey as SurveyRecord
from app.viewer.label_feed import CLUTTER_CORRECTIONS, CLUTTER_DECISIONS, CLUTTER_RUN
from app.viewer.modes.base import Mode
from app.viewer.modes.clutter_camera import ImagePlane
from app.viewer.modes.clutter_hover import HoverTargets
from app.viewer.modes.clutter_images import (
    IMAGE_WIDTHS,
    blank_image,
    mask_thumbnail,
    masked_photo,
    overlay,
    pixel_bbox,
)
from app.viewer.modes.clutter_states import (
    LEGEND,
    SELECTED_RGB,
    STATE_RGB,
    frame_instances,
    point_states,
    run_folder,
    state_colors,
)
from app.viewer.modes.common import checked_user, evenly, legend_html, may, pick_clicked
from app.viewer.modes.pillar_selection import RectangleOptions, rectangle_points
from app.viewer.picking import ScreenCamera

if TYPE_CHECKING:
    from viser import SceneClickEvent, SceneNodeDragEvent, SceneRectSelectEvent

    from app.viewer.session import ViewerSession

FRAME_VIEW = (-12.0, 9.0)  # camera behind the sensor (m along its heading) and above it
ACTIONS = {"Approve": Decision.approved, "Reject": Decision.rejected, "Reset": Decision.pending}
# "Panel width": the viser theme's control width and the panel's width in px (medium: viser's
# own 20 em; large: room for the camera image beside the 3D view)
PANEL_WIDTHS = {"Small": ("small", 256), "Medium": ("medium", 320), "Large": ("large", 760)}
DEFAULT_WIDTH = "Medium"
REMOVE_FROM_INSTANCE = "Remove from instance"
ADD_OBJECT = "Add missed object"
RECTANGLE = RectangleOptions(through=False, near=0.0, far=float("inf"))  # what the user sees
VIEWS = ("Behind the car", "Through the camera")  # where a frame's 3D view looks from
BOX_REDRAW_S = 0.1  # seconds between redraws of a growing box (each is a scene draw)
MIN_BOX_PX = 3.0  # pixels: a narrower box is a slip, dropped


class ClutterMode(Mode):
    name = "Clutter review"
    key = "clutter"

    def enter(self, session: ViewerSession) -> None:
        self.session = session
        self.survey_id = session.view.survey_id
        self.origin = session.view.map.origin
        self.cap = session.viewer.settings.viewer_tile_points
        self.cloud: Any = None
        self.rows: list[Any] = []
        self.states: list[InstanceState] = []
        self.selected: int | None = None  # instance index in the frame
        self.frame_index = 0
        self.panel_width = DEFAULT_WIDTH
        self.raw_photo: np.ndarray | None = None
        self.projection: Projection | None = None
        self.plane: ImagePlane | None = None  # the frame's camera image in the scene
        self.image_node: Any = None
        self.box_node: Any = None
        self.box_from: tuple[float, float] | None = None  # pixel where a box drag started
        self.box_drawn = 0.0
        self.view_fov = float(session.client.camera.fov)  # restored when leaving the camera
        self.targets = HoverTargets(
            session.client.scene, self.key,
            lambda k: session.submit(self.select_target, k),
            lambda event: session.submit(self.on_box, event),
        )  # fmt: skip
        gui = session.client.gui
        self.folder = run_folder(session, self.survey_id)
        if self.folder is None:
            with session.mode_folder:
                gui.add_markdown(
                    "**No clutter run on this survey yet.** Start *run:clutter* from the "
                    "dashboard; its instances show up here for review when it has finished."
                )
            return
        with session.db() as db:
            record = db.get(SurveyRecord, self.survey_id)
            self.frames: list[FrameCount] = clutter_review.frame_counts(db, self.survey_id)
        if not self.frames:
            with session.mode_folder:
                gui.add_markdown("The survey has no frames to review.")
            self.folder = None
            return
        self.survey: Survey = open_survey(record.source_path, record.format)
        self.by_id: dict[str, Frame] = {f.frame_id: f for f in self.survey.frames}
        self.camera = run_camera(self.survey, self.folder)
        self.camera_pose = (
            None if self.camera is None else camera_pose(self.camera.P, self.camera.T_cam_sensor)
        )
        self.run_config = run_config(self.folder)
        self.reviewer = may(session, Role.reviewer)
        self._build_gui()
        start = next((i for i, f in enumerate(self.frames) if f.pending), None)
        if start is None:
            start = next((i for i, f in enumerate(self.frames) if f.instances), 0)
        self.show_frame(start)

    def leave(self) -> None:
        if self.cloud is not None:
            self.cloud.remove()
            self.cloud = None
        for node in (getattr(self, "image_node", None), getattr(self, "box_node", None)):
            if node is not None:
                node.remove()
        if hasattr(self, "targets"):
            self.targets.remove()
        if getattr(self, "view", VIEWS[0]) != VIEWS[0]:
            self.session.client.camera.fov = self.view_fov
        if getattr(self, "panel_width", DEFAULT_WIDTH) != DEFAULT_WIDTH:
            self._apply_width(DEFAULT_WIDTH)  # the other modes get the default panel back

    # --- GUI ----------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        session = self.session
        gui = session.client.gui
        submit = session.submit
        with session.mode_folder:
            self.heading = gui.add_markdown("")
            nav = gui.add_button_group("Frame", ("Previous", "Next", "Next pending"))
            self.width_control = gui.add_button_group("Panel width", tuple(PANEL_WIDTHS))
            self.image = gui.add_image(blank_image(), label="Camera", format="jpeg")
            self.view_control = gui.add_button_group("3D view", VIEWS)
            self.image_in_3d = gui.add_checkbox(
                "Camera image in 3D", False,
                hint="The camera image in the scene on the rays its pixels see; Ctrl-drag a "
                "box on it to add a missed object or cut the selected one",
            )  # fmt: skip
            self.view = VIEWS[0]
            legend = [(n, STATE_RGB[s]) for n, s in LEGEND] + [("selected", SELECTED_RGB)]
            gui.add_html(legend_html(legend))
            self.all_pending = gui.add_button_group(
                "All pending", ("Approve", "Reject"), visible=self.reviewer
            )
            self.instance_folder = gui.add_folder("Instances")
            with gui.add_folder("Selected instance"):
                self.selected_text = gui.add_markdown("Click a point of an instance.")
                self.selected_image = gui.add_image(
                    np.zeros((8, 8, 3), np.uint8), label="Mask", format="png", visible=False
                )
            with gui.add_folder("Correct (shift-drag, Ctrl-drag a box)", visible=self.reviewer):
                self.correct_mode = gui.add_dropdown(
                    "Shift-drag", (REMOVE_FROM_INSTANCE, ADD_OBJECT),
                    hint="Remove the selected instance's points inside the rectangle (or the "
                    "box on the camera image) from it, or make the points inside it that belong "
                    "to no instance (on the image: the object seen most in the box) a new object",
                )  # fmt: skip
                self.object_class = gui.add_dropdown(
                    "New object class", OBJECT_CLASSES, initial_value="car"
                )
            recompute = gui.add_button(
                "Recompute cleaned map",
                hint="Queue clutter:recompute: the maps again from the decisions",
                disabled=not self.reviewer,
            )
            self.point_size = gui.add_slider(
                "Point size", min=0.01, max=0.3, step=0.01, initial_value=0.05
            )
            note = "" if self.reviewer else "Read only: deciding needs the reviewer role. "
            self.status = gui.add_markdown(
                note + "Click a point to select its instance. Shift-drag: rectangle; Ctrl-drag "
                "on the camera image in 3D: box."
            )
        nav.on_click(lambda event: submit(self._navigate, event.target.value))
        self.width_control.on_click(lambda event: submit(self.set_panel_width, event.target.value))
        self.view_control.on_click(lambda event: submit(self.set_view, event.target.value))
        self.image_in_3d.on_update(lambda _: submit(self._draw_image_3d))
        self.all_pending.on_click(
            lambda event: submit(self.decide_pending, ACTIONS[event.target.value])
        )
        recompute.on_click(lambda _: submit(self.recompute))
        self.point_size.on_update(lambda _: submit(self._resize))

    def _navigate(self, action: str) -> None:
        n = len(self.frames)
        if action == "Previous":
            self.show_frame((self.frame_index - 1) % n)
        elif action == "Next":
            self.show_frame((self.frame_index + 1) % n)
        else:
            self.next_pending()

    def _resize(self) -> None:
        if self.cloud is not None:
            self.cloud.point_size = self.point_size.value

    def _apply_width(self, width: str) -> None:
        theme, pixels = PANEL_WIDTHS[width]
        gui = self.session.client.gui
        gui.configure_theme(control_width=theme)
        gui.main_panel.set_width(pixels)
        self.panel_width = width

    def set_panel_width(self, width: str) -> None:
        """Small / Medium / Large: the panel and the camera image drawn at its width."""
        if width not in PANEL_WIDTHS:
            raise ConflictError(f"no panel width {width!r}")
        self._apply_width(width)
        if self.raw_photo is not None:
            self.photo = masked_photo(self.raw_photo, self.states, IMAGE_WIDTHS[width])
            self._draw_images()
        self.session.client.flush()

    def set_view(self, view: str) -> None:
        """Where the 3D view looks from: behind the car, or through the camera (its image
        in the scene, each pixel over the points it sees)."""
        if view not in VIEWS:
            raise ConflictError(f"no 3D view {view!r}")
        if view == VIEWS[1] and self.plane is None:
            self.status.content = "This frame has no camera image to look through."
            return
        self.view = view
        self._draw_image_3d()
        self._look_at_frame(self.by_id[self.frames[self.frame_index].frame_id])
        self.session.client.flush()

    # --- one frame ----------------------------------------------------------------------------

    def show_frame(self, index: int, move_camera: bool = True) -> None:
        """Load frame `index` (points, membership, decisions) and draw it."""
        self.frame_index = index
        self.selected = None
        count = self.frames[index]
        frame = self.by_id.get(count.frame_id)
        if frame is None:
            raise ConflictError(f"frame {count.frame_id} of the store is not in the survey source")
        sensor = frame.points().xyz
        self.sensor_xyz = sensor
        self.xyz = (sensor @ frame.pose[:3, :3].T + frame.pose[:3, 3] - self.origin).astype(
            np.float32
        )
        self.membership = self._membership(count.frame_id, len(sensor))
        self._correct_membership()
        # the budget: every instance point when they fit, and a third at least for the rest
        others = np.flatnonzero(self.owner < 0)
        rest = evenly(others, max(self.cap - int((self.owner >= 0).sum()), self.cap // 3))
        owned = evenly(np.flatnonzero(self.owner >= 0), self.cap - len(rest))
        self.shown = np.sort(np.concatenate([owned, rest]))
        self.projection = self._project(frame)
        self.pixels = None if self.projection is None else self._pixels(self.projection)
        self.plane = (
            None
            if self.projection is None or self.camera_pose is None
            else ImagePlane.of(
                self.camera_pose, frame.pose, self.origin, self.camera.width, self.camera.height
            )
        )
        self._reload_states()
        self.raw_photo = None if self.pixels is None else frame.image(self.camera.name)
        self.photo = (
            None
            if self.raw_photo is None
            else masked_photo(self.raw_photo, self.states, IMAGE_WIDTHS[self.panel_width])
        )
        if self.cloud is not None:
            self.cloud.remove()
        self.cloud = self.session.client.scene.add_point_cloud(
            f"/{self.key}/frame",
            points=self.xyz[self.shown],
            colors=self._colors(),
            point_size=self.point_size.value,
            precision="float32",
            point_shading="flat",
        )
        self._draw_panel()
        self._draw_targets()
        if move_camera:
            self._look_at_frame(frame)
        self.session.client.flush()

    def _membership(self, frame_id: str, n: int) -> RunMembership:
        """The frame's membership as the run wrote it (instance per point, the pipeline's
        removed flag); none where the run wrote no file for the frame."""
        path = self.folder / "instances" / f"{frame_id}.npz"
        if not path.is_file():
            return RunMembership(self.folder, frame_id, np.full(n, -1, np.int32), np.zeros(n, bool))
        with self.session.db() as db:
            membership = clutter_corrections.run_membership(db, self.survey_id, frame_id)
        if len(membership.owner) != n:
            raise ConflictError(
                f"{path}: {len(membership.owner)} points, frame {frame_id} has {n}; "
                "run clutter again"
            )
        return membership

    def _correct_membership(self) -> None:
        """`owner` / `flags`: the run's membership with the reviewers' corrections applied."""
        with self.session.db() as db:
            self.owner, self.flags = clutter_corrections.frame_membership(
                db, self.survey_id, self.membership
            )

    def _project(self, frame: Frame) -> Projection | None:
        """Where the frame's points land in the camera image; None without one."""
        camera = self.camera
        if camera is None or camera.name not in frame.image_paths:
            return None
        return project(self.sensor_xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)

    @staticmethod
    def _pixels(proj: Projection) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) pixel of each point in the camera image (-1 outside)."""
        row = np.full(len(proj.depth), -1, dtype=np.int64)
        col = np.full(len(proj.depth), -1, dtype=np.int64)
        row[proj.in_image], col[proj.in_image] = pixel_indices(proj)
        return row, col

    def _reload_states(self) -> None:
        frame_id = self.frames[self.frame_index].frame_id
        self._correct_membership()
        self.states = frame_instances(self.session, self.survey_id, frame_id)
        self.by_index = {s.instance_index: s for s in self.states}
        self.state = point_states(
            self.owner,
            self.flags,
            np.array([s.instance_index for s in self.states], dtype=np.int64),
            [s.decision for s in self.states],
        )
        pending = sum(s.decision == Decision.pending for s in self.states)
        self.frames[self.frame_index] = FrameCount(frame_id, len(self.states), pending)

    def _colors(self) -> np.ndarray:
        shown = self.shown
        selected = None if self.selected is None else self.owner[shown] == self.selected
        return state_colors(self.state[shown], self.xyz[shown, 2], selected)

    def _look_at_frame(self, frame: Frame) -> None:
        """The 3D view chosen ("3D view"): behind and above the car, or through the camera."""
        camera = self.session.client.camera
        if self.view == VIEWS[1] and self.plane is not None:
            forward = self.plane.rotation[:, 2]
            self.session.move_camera(self.plane.centre + 10.0 * forward, -10.0 * forward)
            screen = ScreenCamera.of(camera)
            camera.fov = self.plane.viewing_fov(screen.width / screen.height)
            return
        if abs(float(camera.fov) - self.view_fov) > 1e-6:
            camera.fov = self.view_fov
        sensor = frame.pose[:3, 3] - self.origin
        heading = frame.pose[:3, 0].copy()
        heading[2] = 0.0
        norm = np.linalg.norm(heading)
        heading = heading / norm if norm > 0 else np.array([1.0, 0.0, 0.0])
        look_at = sensor + 6.0 * heading
        offset = FRAME_VIEW[0] * heading + np.array([0.0, 0.0, FRAME_VIEW[1]])
        self.session.move_camera(look_at, offset)

    def _draw_panel(self) -> None:
        """Heading, camera image, instance list and selection for the current state."""
        self._draw_heading()
        self._draw_images()
        self.image.visible = self.pixels is not None
        self._draw_list()
        self._draw_selected()

    def _draw_images(self) -> None:
        """The overlay image in the panel and, when asked, in the scene."""
        image = self._overlay()
        self.image.image = image
        self._draw_image_3d(image)

    def _draw_image_3d(self, image: np.ndarray | None = None) -> None:
        """The overlay image in the scene on the camera's rays ("Camera image in 3D", always
        when looking through the camera); removed without a camera image or when unticked."""
        wanted = self.plane is not None and (self.image_in_3d.value or self.view == VIEWS[1])
        if not wanted:
            if self.image_node is not None:
                self.image_node.remove()
                self.image_node = None
                self._draw_targets()
            return
        image = self._overlay() if image is None else image
        wxyz, position, width, height = self.plane.node_pose()
        if self.image_node is None:
            self.image_node = self.session.client.scene.add_image(
                f"/{self.key}/camera_image", image, width, height, format="jpeg",
                wxyz=wxyz, position=position, cast_shadow=False, receive_shadow=False,
            )  # fmt: skip
            self.image_node.on_drag("left", modifier="cmd/ctrl")(
                lambda event: self.session.submit(self.on_box, event)
            )
            self._draw_targets()
            return
        self.image_node.image = image
        self.image_node.wxyz, self.image_node.position = wxyz, position
        self.image_node.render_width, self.image_node.render_height = width, height

    def _draw_targets(self) -> None:
        """The instances' hover targets (`clutter_hover`): boxes in 3D, quads on the camera
        image while it is in the scene."""
        if self.cloud is None:
            return
        shown = self.image_node is not None and self.projection is not None
        self.targets.draw(
            self.xyz, self.owner, self.plane if shown else None,
            self.projection.uv if shown else None, self.projection.in_image if shown else None,
        )  # fmt: skip

    def _draw_heading(self) -> None:
        count = self.frames[self.frame_index]
        self.heading.content = (
            f"**Frame {self.frame_index + 1} / {len(self.frames)}** `{count.frame_id}`: "
            f"{count.instances} instances, {count.pending} pending"
        )

    def _overlay(self) -> np.ndarray:
        """The masked camera image with the instances' points dotted by state and the selected
        instance highlighted as in 3D (its points, mask outline and box)."""
        if self.pixels is None or self.photo is None:
            return blank_image()
        selected = None if self.selected is None else self.by_index.get(self.selected)
        return overlay(self.photo, self.pixels, self.owner, self.state, selected, self.raw_photo)

    def _row_label(self, s: InstanceState) -> str:
        mark = "▶ " if s.instance_index == self.selected else ""
        what = f"#{s.instance_index} {s.class_name}, {s.point_count:,} pts"
        return f"{mark}{what}: {s.decision.value}"

    def _draw_list(self) -> None:
        """One button group per instance: select, approve, reject, reset."""
        for row in self.rows:
            row.remove()
        self.rows = []
        gui = self.session.client.gui
        with self.instance_folder:
            if not self.states:
                self.rows.append(gui.add_markdown("No instances in this frame."))
                return
            for s in self.states:
                options = ("Select", "Approve", "Reject", "Reset") if self.reviewer else ("Select",)
                row = gui.add_button_group(self._row_label(s), options)
                row.on_click(
                    lambda event, k=s.instance_index: self.session.submit(
                        self._row_action, k, event.target.value
                    )
                )
                self.rows.append(row)

    def _relabel_rows(self) -> None:
        """Update the list's labels in place (after a selection or decision)."""
        if len(self.rows) != len(self.states) or not self.states:
            self._draw_list()
            return
        for row, s in zip(self.rows, self.states, strict=True):
            label = self._row_label(s)
            if row.label != label:
                row.label = label

    def _row_action(self, instance_index: int, action: str) -> None:
        if action == "Select":
            self.select(instance_index)
            return
        state = self.by_index.get(instance_index)
        if state is not None:
            self.decide([state], ACTIONS[action])

    def _draw_selected(self) -> None:
        s = None if self.selected is None else self.by_index.get(self.selected)
        if s is None:
            self.selected_text.content = "Click a point of an instance (or *Select* in the list)."
            self.selected_image.visible = False
            return
        moving = {True: "moving", False: "static", None: "motion unknown"}[s.moving]
        track = "" if s.track_id is None else f", track {s.track_id}"
        decided = "" if s.user_id is None else f" by user {s.user_id}"
        self.selected_text.content = (
            f"**#{s.instance_index} {s.class_name}**: {s.point_count:,} points, {moving}{track}; "
            f"**{s.decision.value}**{decided} (version {s.version})"
        )
        image = mask_thumbnail(s.mask_path)
        if image is None:
            self.selected_image.visible = False
            return
        self.selected_image.image = image
        self.selected_image.visible = True

    def _refresh(self) -> None:
        """Re-read the frame's decisions and resend colours (never positions) and the panel."""
        self._reload_states()
        if self.cloud is not None:
            self.cloud.colors = self._colors()
        self._draw_heading()
        self._draw_images()
        self._draw_targets()
        self._relabel_rows()
        self._draw_selected()
        self.session.client.flush()

    def on_review_changed(self, actions: set[str]) -> None:
        """Someone decided (re-read the open frame's decisions) or ran clutter again (reload)."""
        if CLUTTER_RUN in actions:
            self.session.reload_mode()
        elif (
            actions & (CLUTTER_DECISIONS | CLUTTER_CORRECTIONS)
            and self.folder is not None
            and self.cloud is not None
        ):
            self._refresh()

    # --- actions ------------------------------------------------------------------------------

    def select(self, instance_index: int | None) -> None:
        self.selected = instance_index
        self._refresh()

    def select_target(self, instance_index: int) -> None:
        """A click on an instance's hover target (its box in 3D, its box on the image)."""
        self.select(instance_index)
        state = self.by_index.get(instance_index)
        if state is not None:
            self.status.content = f"Selected #{instance_index} ({state.class_name})."

    def on_click(self, event: SceneClickEvent) -> None:
        """Select the instance of the clicked point (the nearest shown point along the ray)."""
        if self.folder is None or self.cloud is None:
            return
        hit = pick_clicked(self.xyz[self.shown], event, self.point_size.value)
        if hit < 0:
            self.status.content = "No point under the click."
            return
        instance = int(self.owner[self.shown[hit]])
        if instance < 0 or instance not in self.by_index:
            self.status.content = "That point belongs to no instance."
            return
        self.select(instance)
        self.status.content = f"Selected #{instance} ({self.by_index[instance].class_name})."

    def on_rect_select(self, event: SceneRectSelectEvent) -> None:
        """Shift-drag: correct the selected instance, or add a missed object (reviewers), with
        the shown points inside the rectangle that the camera sees."""
        if self.folder is None or self.cloud is None:
            return
        checked_user(self.session, Role.reviewer, "correcting clutter instances")
        inside = rectangle_points(
            self.xyz[self.shown], event.client.camera, event.screen_min, event.screen_max,
            float(self.point_size.value), RECTANGLE,
        )  # fmt: skip
        points = self.shown[inside]
        if self.correct_mode.value == ADD_OBJECT:
            self.add_object(points, self.object_class.value)
        else:
            self.remove_from_selected(points)

    def on_box(self, event: SceneNodeDragEvent) -> None:
        """Ctrl-drag on the camera image in 3D: a 2D box, drawn as it grows; at release it
        adds the object the camera sees most in it, or cuts the selected instance (the mode
        "Shift-drag" names)."""
        plane = self.plane
        if plane is None:
            return
        start = np.asarray(event.start_position, dtype=np.float64)
        if event.phase == "start":
            self.box_from = None
            if not plane.holds(start):
                return  # a drag from an instance's box in 3D, not from the image: no 2D box
            if not self.reviewer:
                self.status.content = "Correcting instances needs the reviewer role."
                return
            self.box_from = plane.pixel_of(start)
        screen = ScreenCamera.of(self.session.client.camera)
        end = plane.pixel_under(screen, event.end_screen_pos)
        if event.phase == "end" and not plane.holds(start):
            return
        if event.phase == "end" and (self.box_from is None or end is None):
            self.box_from = None
            self._draw_box(np.zeros((0, 2, 3)))
            if self.reviewer:
                self.status.content = "Box dropped: it ended off the camera image."
            return
        if self.box_from is None or end is None:
            return
        if event.phase != "end":
            now = time.perf_counter()
            if now - self.box_drawn >= BOX_REDRAW_S:
                self.box_drawn = now
                self._draw_box(plane.box_outline(self.box_from, end))
            return
        box = PixelBox.spanning(self.box_from, end).clipped(plane.width, plane.height)
        self.box_from = None
        self._draw_box(np.zeros((0, 2, 3)))
        if min(box.u1 - box.u0, box.v1 - box.v0) < MIN_BOX_PX:
            self.status.content = "Box dropped: Ctrl-drag across the object on the image."
            return
        self.correct_in_box(box)

    def _draw_box(self, segments: np.ndarray) -> None:
        if self.box_node is not None:
            self.box_node.remove()
            self.box_node = None
        if len(segments):
            self.box_node = self.session.client.scene.add_line_segments(
                f"/{self.key}/box", points=segments.astype(np.float32), colors=SELECTED_RGB,
                thickness=3.0, thickness_units="screen",
            )  # fmt: skip

    def correct_in_box(self, box: PixelBox) -> None:
        """A box on the camera image (pixels): add the object seen most in it, or take the
        selected instance's points in it out of it."""
        checked_user(self.session, Role.reviewer, "correcting clutter instances")
        if self.projection is None:
            self.status.content = "This frame has no camera image."
            return
        if self.correct_mode.value == ADD_OBJECT:
            found = object_in_box(
                self.sensor_xyz, self.projection, self.owner, box, self.run_config
            )
            if not len(found):
                self.status.content = (
                    "No object free of an instance above the ground in the box: draw it round "
                    "a missed one."
                )
                return
            self.add_object(found, self.object_class.value, box.as_bbox())
            return
        inside = np.flatnonzero(self.projection.in_image & box.holds(self.projection.uv))
        self.remove_from_selected(inside)

    def remove_from_selected(self, points: np.ndarray) -> None:
        """Take the selected instance's points among `points` (frame indices) out of it."""
        user = checked_user(self.session, Role.reviewer, "correcting clutter instances")
        state = None if self.selected is None else self.by_index.get(self.selected)
        if state is None:
            self.status.content = "Select an instance first, then shift-drag over its points."
            return
        mine = points[self.owner[points] == state.instance_index]
        if not len(mine):
            self.status.content = f"No point of #{state.instance_index} inside the selection."
            return
        try:
            with self.session.db() as db:
                done = clutter_corrections.remove_points(
                    db, self.survey_id, state.id, state.version, mine, user.id, self.membership
                )
        except StaleWriteError as exc:
            self._stale(exc)
            return
        self.session.viewer.labels_written()  # other clients follow now
        self.status.content = (
            f"{done.points:,} point(s) taken out of #{state.instance_index}: they stay in the map."
        )
        self._refresh()

    def add_object(
        self, points: np.ndarray, class_name: str, bbox: list[int] | None = None
    ) -> None:
        """A missed object: the points among `points` that belong to no instance become a new
        instance of `class_name` on this frame, approved, and selected; `bbox` its box on the
        image (else its points' box)."""
        user = checked_user(self.session, Role.reviewer, "adding clutter objects")
        free = points[self.owner[points] < 0]
        if not len(free):
            self.status.content = "No point inside the selection is free of an instance."
            return
        if bbox is None and self.pixels is not None:
            bbox = pixel_bbox(self.pixels, free)
        frame_id = self.frames[self.frame_index].frame_id
        try:
            with self.session.db() as db:
                done = clutter_corrections.add_object(
                    db, self.survey_id, frame_id, class_name, free, user.id, self.membership, bbox
                )
        except StaleWriteError as exc:
            self._stale(exc)
            return
        self.session.viewer.labels_written()
        self.selected = done.state.instance_index
        self.status.content = (
            f"Added #{done.state.instance_index} {class_name} of {done.points:,} point(s), "
            "approved: recompute removes them."
        )
        self._refresh()

    def _stale(self, exc: StaleWriteError) -> None:
        self.session.notify("Changed meanwhile", f"{exc.message} (reloaded)", error=True)
        self.status.content = "Someone else changed it first: the frame was reloaded."
        self._refresh()

    def decide(self, states: Sequence[InstanceState], decision: Decision) -> None:
        """One versioned batch through the store; stale -> re-read and tell the reviewer."""
        if not states:
            self.status.content = "Nothing to decide."
            return
        user = checked_user(self.session, Role.reviewer, "deciding on clutter")
        writes = [DecisionWrite(s.id, s.version, decision) for s in states]
        try:
            with self.session.db() as db:
                clutter_review.decide(db, self.survey_id, writes, user.id)
            self.session.viewer.labels_written()  # other clients follow now
        except StaleWriteError as exc:
            self.session.notify("Changed meanwhile", f"{exc.message} (reloaded)", error=True)
            self.status.content = "Someone else decided first: the frame was reloaded."
            self._refresh()
            return
        self.status.content = f"{len(states)} instance(s) {decision.value}."
        self._refresh()

    def decide_pending(self, decision: Decision) -> None:
        self.decide([s for s in self.states if s.decision == Decision.pending], decision)

    def next_pending(self) -> None:
        """The next frame (after this one, wrapping) that still has pending instances."""
        with self.session.db() as db:
            self.frames = clutter_review.frame_counts(db, self.survey_id)
        n = len(self.frames)
        for step in range(1, n + 1):
            i = (self.frame_index + step) % n
            if self.frames[i].pending:
                self.show_frame(i)
                return
        self.status.content = "No frame has pending instances: the review is complete."

    def recompute(self) -> None:
        """Queue clutter:recompute (reviewer): the cleaned map from the decisions."""
        user = checked_user(self.session, Role.reviewer, "recomputing the cleaned map")
        settings = self.session.viewer.settings
        with self.session.db() as db:
            if not clutter_review.has_review(db, self.survey_id):
                raise ConflictError(f"survey {self.survey_id} has no clutter run to review")
            job = enqueue(db, clutter_review.RECOMPUTE_KIND, {}, self.survey_id, user.id, settings)
        self.status.content = f"Queued job {job.id} ({job.kind}): see the dashboard's jobs."
        self.session.notify("Recompute queued", f"job {job.id}: {job.kind}")
