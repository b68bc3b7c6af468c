"""Pillar labelling: paint the phantom paper's four pillar classes onto the map.

The map is shown as two float32 point clouds re-centred on the survey origin: a voxel-downsampled
overview of the whole survey and the full-resolution points of the 50 m tile in focus (where the
camera looks or the last brush stroke landed; loaded when the focus moves to another tile).
Points are coloured by their pillar's label: human labels in full colour, model pre-labels
lighter, unlabelled grey. A label change anywhere resends colours only.

Tools: a class palette (hotkeys 1-4, 0 erases); click tools (B G P M I, `pillar_tools`): the
brush (every pillar within the radius of the surface point under the cursor, or of the ground
where there is none; one undoable batch), fill (the pillars connected through small height
steps), polygon (clicks, Enter closes), measure and inspect; the rectangle (shift-drag: the
pillars of the shown points inside it that the user can see, within a depth range,
`pillar_selection`) and the free-hand lasso (Ctrl-drag, the same test inside the path drawn:
the drag is caught by an invisible plane under the map, the only kind of scene node viser
reports drags on). A selection over CONFIRM_ABOVE pillars is previewed and written on Enter.
"Apply to" locks pillars: only unlabelled ones, or only one class, are written. Undo / redo
(Ctrl+Z / Ctrl+Y, the user's own batches in the store); "next uncertain area" (N) flies the
camera to the area whose unreviewed model pre-labels are least confident and outlines it; H
shows the shortcut sheet.

Display: colour by label, height above ground, intensity, model confidence or the camera's
colour (`colour_modes`);
a height slice (only points between two heights above the ground are shown, and so selectable:
label under trees and canopies); rounded points (a depth cue on dense scans); top and side
views of the focus beside the 3D view (`mini_views`), in the same colours; after a measurement
the side view is the cross-section along the measured line.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from app.core.errors import StaleWriteError
from app.core.labels import PillarClass
from app.store.pillar_labels import NO_LABEL, STORE_GRID
from app.store.pillar_reads import label_counts, uncertain_areas
from app.viewer.colour_modes import (
    CAMERA,
    COLOUR_MODES,
    CONFIDENCE,
    HEIGHT,
    INTENSITY,
    LABEL,
    camera_colors,
    confidence_colors,
    height_colors,
    intensity_colors,
)
from app.viewer.mini_views import HALF_WIDTH, SLAB, side_view, top_view, within_square
from app.viewer.modes.base import Mode
from app.viewer.modes.common import TARGET_RGB
from app.viewer.modes.pillar_selection import (
    CONFIRM_ABOVE,
    PendingSelection,
    RectangleOptions,
    rectangle_points,
)
from app.viewer.modes.pillar_tools import (
    FILL_RADIUS,
    FILL_STEP,
    fill_region,
    measure_text,
    pillar_tops,
)
from app.viewer.picking import (
    ScreenCamera,
    click_angle,
    pick_on_ray,
    pillars_in_disc,
    ray_ground_hit,
)
from app.viewer.pillar_colors import CLASS_NAMES, DISPLAY_CLASSES, DISPLAY_NAMES, swatch_html
from app.viewer.shown_points import ShownPoints
from app.viewer.view_presets import heading_at

if TYPE_CHECKING:
    from viser import CameraHandle, SceneClickEvent, SceneNodeDragEvent, SceneRectSelectEvent

    from app.viewer.session import ViewerSession

ERASE = "Erase"
CHOICES = {**{name: int(c) for c, name in CLASS_NAMES.items()}, ERASE: NO_LABEL}
HOTKEYS = {"1": "Ground", "2": "High object", "3": "Short object", "4": "Phantom", "0": ERASE}
UNCERTAIN_VIEW_DISTANCE = 25.0  # metres from the camera to an uncertain area
UNCERTAIN_AREA = 10.0  # metres: the side of an uncertain area
AREA_HEIGHT = 4.0  # metres: the outline's height above the ground
MAX_DEPTH = 500.0  # metres: the depth range slider's end
BRUSH, FILL, POLYGON, MEASURE, INSPECT = "Brush", "Fill", "Polygon", "Measure", "Inspect"
TOOLS = (BRUSH, FILL, POLYGON, MEASURE, INSPECT)
TOOL_KEYS = {"B": BRUSH, "G": FILL, "P": POLYGON, "M": MEASURE, "I": INSPECT}
APPLY_TO = ("All pillars", "Unlabelled only", *(f"Only {n.lower()}" for n in CLASS_NAMES.values()))
MARK_RGB = (20, 20, 20)  # polygon vertices, measured points, the brush ring
SHORTCUTS = """| key | action |
|---|---|
| 1 2 3 4 / 0 | class: ground, high object, short object, phantom / erase |
| B G P M I | click tool: brush, fill, polygon, measure, inspect |
| shift-drag | rectangle (what you see; a large one waits for Enter) |
| Ctrl-drag | lasso: free-hand, what you see inside the path |
| Enter / Esc | apply / drop a previewed selection; Enter closes a polygon |
| Ctrl+Z / Ctrl+Y | undo / redo your last labelling action |
| N | next uncertain area |
| T F S O | top, front, side, oblique view |
| H | this sheet |"""
SIDE_LABEL = "Side (from the right, 4 m slab)"
SECTION_MAX = 30.0  # metres each way from the middle of a measured line's cross-section
VIEWS_MOVE = 0.5  # metres the focus moves before the top / side views are redrawn
HEIGHT_SLICE = (-2.0, 40.0)  # metres above the ground: the height slice slider's ends
LASSO_MARGIN = 1000.0  # metres the lasso's catch plane reaches past the map on every side
LASSO_BELOW = 1.0  # metres the catch plane lies below the map's lowest point
# seconds between redraws of a growing lasso's path: the page reports the pointer at 20 Hz, and
# every redraw makes the browser draw the whole scene again (a second per frame in software
# WebGL on a real street: a scripted lasso round a group took about 15 s at 20 Hz, 10-13 s so)
LASSO_REDRAW_S = 0.2


class PillarMode(Mode):
    name = "Pillar labelling"
    key = "pillars"

    def enter(self, session: ViewerSession) -> None:
        self.session = session
        self.view = session.view
        self.map = self.view.map
        self.tile_cap = session.viewer.settings.viewer_tile_points
        self.hidden: set[int] = set()
        self.tile_id: int | None = None
        self.tile_points = np.zeros(0, dtype=np.int64)
        self.shown = {"overview": ShownPoints.empty(), "tile": ShownPoints.empty()}
        self._all_shown: ShownPoints | None = None
        self.clouds: dict[str, Any] = {}
        self.visited: set[tuple[float, float]] = set()
        self.commands: list[Any] = []
        self.pending: PendingSelection | None = None
        self.area_outline: Any = None
        self.height_slice = HEIGHT_SLICE
        self.colour_by = LABEL
        self.views_at: np.ndarray | None = None  # the focus the top / side views show
        self.views_due = False  # a redraw of the views is queued (`_views_later`)
        self.marks: dict[str, Any] = {}  # line segments: brush ring, polygon, measurement
        self.brush_at: np.ndarray | None = None
        self.polygon: list[np.ndarray] = []  # local vertices of the polygon being drawn
        self.lasso: list[tuple[float, float]] = []  # screen positions (0-1) of a lasso drag
        self.lasso_path: list[np.ndarray] = []  # the same, on the drag plane (local, drawn)
        self.lasso_drawn = 0.0  # when the growing path was last drawn (perf_counter)
        self.measured: list[np.ndarray] = []
        self.section: tuple[np.ndarray, np.ndarray] | None = None  # the last measured line
        self._build_gui()
        self.catch = self._lasso_catch()
        self._draw("overview", self.map.overview)
        self._focus(session.client.camera.look_at)
        self._draw_views()

    def leave(self) -> None:
        self._drop_pending()
        self.catch.remove()
        for mark in self.marks.values():
            mark.remove()
        self.marks = {}
        if self.area_outline is not None:
            self.area_outline.remove()
            self.area_outline = None
        for command in self.commands:
            command.remove()
        self.commands = []
        for cloud in self.clouds.values():
            cloud.remove()
        self.clouds = {}

    # --- GUI ----------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        session = self.session
        gui = session.client.gui
        with session.mode_folder:
            legend = "".join(
                f"<div>{swatch_html(k)}{DISPLAY_NAMES[k]}</div>" for k in DISPLAY_CLASSES
            )
            gui.add_html(
                f'<div style="font-size:0.8em;padding:0 0.5em">{legend}'
                "<div>lighter: model pre-label (paler = less sure)</div></div>"
            )
            self.klass = gui.add_dropdown("Class (1-4, 0)", tuple(CHOICES), initial_value="Ground")
            self.tool = gui.add_dropdown(
                "Click tool (B G P M I)", TOOLS, initial_value=BRUSH,
                hint="what a click does; shift-drag is always the rectangle",
            )  # fmt: skip
            self.apply_to = gui.add_dropdown(
                "Apply to", APPLY_TO, initial_value=APPLY_TO[0],
                hint="lock the other pillars: label only unlabelled ones, or only one class",
            )  # fmt: skip
            self.radius = gui.add_slider(
                "Brush radius (m)", min=0.2, max=10.0, step=0.2, initial_value=1.0
            )
            self.fill_step = gui.add_slider(
                "Fill step (m)", min=0.02, max=1.0, step=0.01, initial_value=FILL_STEP,
                hint="the largest height step between neighbouring pillars a fill crosses",
            )  # fmt: skip
            undo = gui.add_button("Undo (Ctrl+Z)", hint="revert your last labelling action")
            redo = gui.add_button("Redo (Ctrl+Y)", hint="re-apply what you undid")
            jump = gui.add_button("Next uncertain area (N)", hint="least confident model labels")
            shortcuts = gui.add_button("Keyboard shortcuts (H)")
            self.status = gui.add_markdown("Click: brush. Shift-drag: rectangle. Ctrl-drag: lasso.")
            with gui.add_folder("Rectangle", expand_by_default=False):
                self.through = gui.add_checkbox(
                    "Select hidden points too",
                    initial_value=False,
                    hint="off: only what you see; on: also points behind nearer ones",
                )
                self.depth_range = gui.add_multi_slider(
                    "Depth range (m)", min=0.0, max=MAX_DEPTH, step=1.0,
                    initial_value=(0.0, MAX_DEPTH),
                    hint="only points this far from the camera",
                )  # fmt: skip
            self.apply_selection = gui.add_button(
                "Apply selection (Enter)", disabled=True, hint="label the previewed pillars"
            )
            self.cancel_selection = gui.add_button(
                "Cancel selection (Esc)", disabled=True, hint="drop the preview or the polygon"
            )
            with gui.add_folder("Top and side views", expand_by_default=True):
                self.show_views = gui.add_checkbox("Show", initial_value=True)
                blank = np.full((10, 10, 3), 255, dtype=np.uint8)
                self.top_image = gui.add_image(blank, label="Top (drive up)", format="png")
                self.side_image = gui.add_image(blank, label=SIDE_LABEL, format="png")
            with gui.add_folder("Display", expand_by_default=False):
                self.colour_menu = gui.add_dropdown("Colour by", COLOUR_MODES, initial_value=LABEL)
                self.height_slider = gui.add_multi_slider(
                    "Height slice (m)", min=HEIGHT_SLICE[0], max=HEIGHT_SLICE[1], step=0.1,
                    initial_value=HEIGHT_SLICE, hint="show only points this high above the ground",
                )  # fmt: skip
                self.rounded = gui.add_checkbox(
                    "Rounded points", initial_value=False, hint="shaded discs: a depth cue"
                )
                self.point_size = gui.add_slider(
                    "Point size", min=0.01, max=0.5, step=0.01, initial_value=0.06
                )
                self.hide = {
                    k: gui.add_checkbox(f"Hide {DISPLAY_NAMES[k].lower()}", initial_value=False)
                    for k in DISPLAY_CLASSES
                }
        submit = session.submit
        undo.on_click(lambda _: submit(self.undo))
        redo.on_click(lambda _: submit(self.redo))
        jump.on_click(lambda _: submit(self.next_uncertain_area))
        shortcuts.on_click(lambda _: submit(self.show_shortcuts))
        self.radius.on_update(lambda _: submit(self._draw_brush_ring))
        self.apply_selection.on_click(lambda _: submit(self.confirm_selection))
        self.cancel_selection.on_click(lambda _: submit(self.cancel_pending))
        self.point_size.on_update(lambda _: submit(self._resize_points))
        for checkbox in self.hide.values():
            checkbox.on_update(lambda _: submit(self._apply_hidden))
        self.height_slider.on_update(lambda _: submit(self._apply_hidden))
        self.colour_menu.on_update(lambda _: submit(self._apply_colour_mode))
        self.rounded.on_update(lambda _: submit(self._apply_shading))
        self.show_views.on_update(lambda _: submit(self._draw_views))
        for key, choice in HOTKEYS.items():
            self._command(f"Class: {choice}", key, None, lambda c=choice: self._pick(c))
        self._command("Undo", "Z", "cmd/ctrl", lambda: submit(self.undo))
        self._command("Redo", "Y", "cmd/ctrl", lambda: submit(self.redo))
        self._command("Next uncertain area", "N", None, lambda: submit(self.next_uncertain_area))
        self._command("Apply selection", "enter", None, lambda: submit(self.confirm_selection))
        self._command("Cancel selection", "escape", None, lambda: submit(self.cancel_pending))
        for key, tool in TOOL_KEYS.items():
            self._command(f"Tool: {tool}", key, None, lambda t=tool: self._pick_tool(t))
        self._command("Keyboard shortcuts", "H", None, lambda: submit(self.show_shortcuts))

    def _command(self, label: str, hotkey: str, modifier: str | None, action: Any) -> None:
        command = self.session.client.gui.add_command(label, hotkey=hotkey, modifier=modifier)
        command.on_trigger(lambda _: action())
        self.commands.append(command)

    def _pick(self, choice: str) -> None:
        self.klass.value = choice

    def _pick_tool(self, tool: str) -> None:
        self.tool.value = tool

    def show_shortcuts(self) -> None:
        """The keyboard shortcut sheet, in a modal."""
        with self.session.client.gui.add_modal("Keyboard shortcuts") as modal:
            self.session.client.gui.add_markdown(SHORTCUTS)
            self.session.client.gui.add_button("Close").on_click(lambda _: modal.close())

    @property
    def label_value(self) -> int:
        return CHOICES[self.klass.value]

    # --- drawing ------------------------------------------------------------------------------

    def _visible(self, points: np.ndarray) -> np.ndarray:
        """The points not hidden by class or outside the height slice."""
        if not len(points):
            return points
        if self.hidden:
            points = points[~np.isin(self.view.point_classes(points), list(self.hidden))]
        if self.height_slice != HEIGHT_SLICE:
            height = self._height_above_ground(points)
            lo, hi = self.height_slice
            points = points[(height >= lo) & (height <= hi)]
        return points

    def _height_above_ground(self, points: np.ndarray) -> np.ndarray:
        return self._height_of(np.asarray(self.map.xyz[points]))

    def _height_of(self, xyz: np.ndarray) -> np.ndarray:
        xyz = np.asarray(xyz, dtype=np.float64)
        return xyz[:, 2] - self.map.ground.height(xyz[:, :2])

    def _colors(self, shown: ShownPoints) -> np.ndarray:
        """(n, 3) uint8 colours of shown points in the chosen colour mode."""
        if self.colour_by == HEIGHT:
            return height_colors(self._height_of(shown.xyz))
        if self.colour_by == INTENSITY:
            return intensity_colors(np.asarray(self.map.intensity[shown.index]))
        if self.colour_by == CONFIDENCE:
            return confidence_colors(self.view.pillar_confidence(shown.cell))
        if self.colour_by == CAMERA:
            index = shown.index
            return camera_colors(np.asarray(self.map.rgb[index]), self.map.has_rgb[index])
        return self.view.pillar_rgb(shown.cell)

    @property
    def shown_overview(self) -> np.ndarray:
        return self.shown["overview"].index

    @property
    def shown_tile(self) -> np.ndarray:
        return self.shown["tile"].index

    def _shown(self) -> ShownPoints:
        """Every shown point, the overview's then the tile's."""
        if self._all_shown is None:
            self._all_shown = ShownPoints.join([self.shown["overview"], self.shown["tile"]])
        return self._all_shown

    def _draw(self, name: str, points: np.ndarray) -> None:
        """(Re)send one cloud (positions and colours) with the points of `points` not hidden."""
        shown = ShownPoints.gather(self.map, self._visible(points))
        self.shown[name] = shown
        self._all_shown = None
        old = self.clouds.pop(name, None)
        if old is not None:
            old.remove()
        if len(shown):
            self.clouds[name] = self.session.client.scene.add_point_cloud(
                f"/{self.key}/{name}",
                points=shown.xyz,
                colors=self._colors(shown),
                point_size=self.point_size.value,
                precision="float32",
                point_shading="gradient" if self.rounded.value else "flat",
            )

    def _focus(self, xy_local: np.ndarray) -> None:
        """Show the full-resolution points of the tile holding xy (when it is another tile)."""
        if not len(self.map):
            return
        tile = self.map.tile_id_at(np.asarray(xy_local)[:2])
        if tile == self.tile_id:
            return
        self.tile_id = tile
        points = self.map.tile_points(tile)
        if len(points) > self.tile_cap:  # evenly spread subset, the same every time
            points = points[np.linspace(0, len(points) - 1, self.tile_cap).astype(np.int64)]
        self.tile_points = points
        self._draw("tile", points)
        self.session.client.flush()

    def _resize_points(self) -> None:
        for cloud in self.clouds.values():
            cloud.point_size = self.point_size.value
        if self.pending is not None:
            self.pending.resize(self.point_size.value)

    def _apply_hidden(self) -> None:
        hidden = {k for k, box in self.hide.items() if box.value}
        height_slice = tuple(float(v) for v in self.height_slider.value)
        if hidden == self.hidden and height_slice == self.height_slice:
            return
        self.hidden, self.height_slice = hidden, height_slice
        self._redraw()

    def _redraw(self) -> None:
        self._draw("overview", self.map.overview)
        self._draw("tile", self.tile_points)
        self._draw_pending()
        self._draw_views()

    def _apply_colour_mode(self) -> None:
        self.colour_by = self.colour_menu.value
        if self.colour_by == INTENSITY and not np.isfinite(self.map.intensity[:1_000]).any():
            self.status.content = "This survey recorded no intensity: its points are grey."
        if self.colour_by == CAMERA and not self.map.has_rgb[self.map.overview].any():
            self.status.content = "No camera image saw these points: they are grey."
        for name in ("overview", "tile"):
            cloud = self.clouds.get(name)
            if cloud is not None:
                cloud.colors = self._colors(self.shown[name])
        self._draw_views()

    def _apply_shading(self) -> None:
        for cloud in self.clouds.values():
            cloud.point_shading = "gradient" if self.rounded.value else "flat"

    def _draw_views(self) -> None:
        """The top image of the points around the camera's focus and the side image: along the
        drive there, or the cross-section along the last measured line (`mini_views`)."""
        self.top_image.visible = self.side_image.visible = bool(self.show_views.value)
        if not self.show_views.value or not len(self.map):
            return
        camera = self.session.client.camera
        focus = np.asarray(camera.look_at, dtype=np.float64)
        shown = self._shown()
        heading = heading_at(self.session.trajectory, focus[:2])
        near = shown.take(within_square(shown.xyz, focus, HALF_WIDTH * 1.5))
        rgb = self._colors(near)
        self.top_image.image = top_view(near.xyz, rgb, focus, heading)
        if self.section is None:
            self.side_image.label = SIDE_LABEL
            self.side_image.image = side_view(near.xyz, rgb, focus, heading)
            return
        a, b = self.section
        middle, half = (a + b) / 2.0, min(float(np.hypot(*(b - a)[:2])) / 2.0 + 1.0, SECTION_MAX)
        cut = shown.take(within_square(shown.xyz, middle, half + SLAB))
        self.side_image.label = f"Section along the measured line ({2 * half:.0f} m)"
        self.side_image.image = side_view(
            cut.xyz, self._colors(cut), middle, b - a, half_width=half
        )

    def on_labels_changed(self, changed: np.ndarray) -> None:
        """Resend the colours of the clouds holding changed pillars (with classes hidden, a
        relabelled pillar may appear or vanish: that cloud is resent whole); colours by height
        or intensity do not change with labels."""
        mark = np.zeros(len(self.map.cells), dtype=bool)
        mark[changed] = True
        by_label = self.colour_by in (LABEL, CONFIDENCE)
        touched = False
        for name, source in (("overview", self.map.overview), ("tile", self.tile_points)):
            shown = self.shown[name]
            if self.hidden:
                visible = self._visible(source)
                if not np.array_equal(visible, shown.index):
                    self._draw(name, source)
                    touched = True
                    continue
            cloud = self.clouds.get(name)
            if by_label and cloud is not None and mark[shown.cell].any():
                cloud.colors = self._colors(shown)
                touched = True
        if touched:
            self.session.client.flush()  # the colours first: the views can follow
            self._views_later()

    def _views_later(self) -> None:
        """Redraw the top and side views after the work in hand (a write's store commit and
        its status line), once however many label changes come before it runs: they take a
        tenth of a second on a real street, which the next click would otherwise wait for."""
        if not self.views_due:
            self.views_due = True
            self.session.submit(self._draw_due_views)

    def _draw_due_views(self) -> None:
        self.views_due = False
        if self.session.mode is self:  # not left meanwhile
            self._draw_views()

    # --- tools --------------------------------------------------------------------------------

    def on_camera(self, camera: CameraHandle) -> None:
        self._focus(camera.look_at)
        focus = np.asarray(camera.look_at, dtype=np.float64)
        if self.views_at is None or np.abs(focus - self.views_at).max() > VIEWS_MOVE:
            self.views_at = focus
            self._draw_views()

    def _surface_hit(self, event: SceneClickEvent) -> np.ndarray | None:
        """(3,) local point a click means: on the click ray (exactly under the cursor) at the
        depth of the surface drawn there (the shown point picked), else where the ray meets the
        ground; None when it meets neither. The picked point itself may lie a few pixels off
        the cursor: a brush or a polygon vertex there would land beside what the user meant."""
        shown = self._shown()
        angle = click_angle(event.client.camera)
        origin = np.asarray(event.ray_origin, dtype=np.float64)
        direction = np.asarray(event.ray_direction, dtype=np.float64)
        hit_point = pick_on_ray(shown.xyz, origin, direction, angle, float(self.point_size.value))
        if hit_point < 0:
            return ray_ground_hit(self.map.ground, origin, direction)
        direction = direction / np.linalg.norm(direction)
        depth = float((shown.xyz[hit_point].astype(np.float64) - origin) @ direction)
        return origin + depth * direction

    def on_click(self, event: SceneClickEvent) -> None:
        """The click tool's action at the point under the cursor."""
        hit = self._surface_hit(event)
        tool = self.tool.value
        if hit is None:
            self.session.notify(tool, "The click met no point and not the ground.")
            return
        {
            BRUSH: self._brush, FILL: self._fill, POLYGON: self._add_vertex,
            MEASURE: self._measure, INSPECT: self._inspect,
        }[tool](hit)  # fmt: skip

    def _brush(self, hit: np.ndarray) -> None:
        """Brush: the pillars within the radius of the point hit."""
        self.brush_at = hit
        self._draw_brush_ring()
        world = hit[:2] + self.map.origin[:2]
        cells = pillars_in_disc(world, float(self.radius.value))
        cells = cells[self.map.cell_index(cells)[1]]  # pillars that hold points
        if not len(cells):
            self.session.notify("Brush", "No points under the brush.")
            return
        self._label(cells, f"brush r = {self.radius.value:.1f} m")
        self._focus(hit)

    def _draw_brush_ring(self) -> None:
        """The brush's reach, a ring on the ground where it last painted."""
        if self.brush_at is None:
            return
        angle = np.linspace(0.0, 2.0 * np.pi, 49)
        r = float(self.radius.value)
        ring = np.stack([r * np.cos(angle), r * np.sin(angle), np.zeros_like(angle)], axis=1)
        ring += self.brush_at
        ring[:, 2] = self.map.ground.height(ring[:, :2]) + 0.05
        self._mark("brush_ring", np.stack([ring[:-1], ring[1:]], axis=1))

    def _mark(self, name: str, segments: np.ndarray) -> None:
        """(Re)draw line segments (k, 2, 3) as the scene node `name` (empty: remove it)."""
        old = self.marks.pop(name, None)
        if old is not None:
            old.remove()
        if len(segments):
            self.marks[name] = self.session.client.scene.add_line_segments(
                f"/{self.key}/marks/{name}",
                points=np.asarray(segments, dtype=np.float32),
                colors=MARK_RGB,
                thickness=2.0,
                thickness_units="screen",
            )

    def _fill(self, hit: np.ndarray) -> None:
        """Fill: the pillars connected to the one hit through small height steps (shown
        points within FILL_RADIUS), previewed like a large rectangle."""
        shown = self._shown()
        near = shown.take(np.hypot(*(shown.xyz[:, :2] - hit[:2]).T) <= FILL_RADIUS)
        cells, top = pillar_tops(self.map.cells, near.cell, near.xyz[:, 2])
        seed = int(STORE_GRID.point_cell_ids((hit[:2] + self.map.origin[:2])[None])[0])
        region = fill_region(cells, top, seed, float(self.fill_step.value))
        if not len(region):
            self.status.content = "Fill: no shown pillar under the click."
            return
        self._select(region, f"fill, step {self.fill_step.value:.2f} m")

    def _add_vertex(self, hit: np.ndarray) -> None:
        """Polygon: one more vertex; Enter closes it."""
        self.polygon.append(hit)
        vertices = np.asarray(self.polygon)
        closed = np.vstack([vertices, vertices[:1]])
        self._mark("polygon", np.stack([closed[:-1], closed[1:]], axis=1))
        self.status.content = (
            f"Polygon: {len(self.polygon)} vertices. Click to add, **Enter** to close "
            "(3 or more), **Esc** to drop."
        )

    def _close_polygon(self) -> None:
        """The pillars of the visible shown points inside the polygon, projected with the
        camera now."""
        screen = ScreenCamera.of(self.session.client.camera)
        corners_px, depth = screen.project(np.asarray(self.polygon))
        self.polygon = []
        self._mark("polygon", np.zeros((0, 2, 3)))
        if (depth <= 0).any():
            self.status.content = "Polygon dropped: a vertex is behind the camera."
            return
        self._select_inside(corners_px, screen, "polygon")

    def _cells_of(self, pillar: np.ndarray) -> np.ndarray:
        """Store cell ids (sorted, unique) of points' pillar indices into the map's pillars: a
        mark per pillar, not a sort of the points (a street-wide rectangle holds 500,000)."""
        marked = np.zeros(len(self.map.cells), dtype=bool)
        marked[pillar] = True
        return self.map.cells[marked]

    def _select_inside(self, corners_px: np.ndarray, screen: ScreenCamera, how: str) -> None:
        """The pillars of the visible shown points inside a closed screen polygon (pixels):
        the rectangle's test (depth, hidden points, depth range) on its bounding box, then the
        polygon's own outline."""
        size = np.array([screen.width, screen.height])
        shown = self._shown()
        xyz = shown.xyz
        lo, hi = corners_px.min(axis=0) / size, corners_px.max(axis=0) / size
        inside = rectangle_points(
            xyz, self.session.client.camera, tuple(lo), tuple(hi),
            float(self.point_size.value), self._rectangle_options(), outline=corners_px,
        )  # fmt: skip
        cells = self._cells_of(shown.cell[inside])
        if not len(cells):
            self.status.content = f"No visible points inside the {how}."
            return
        self._select(cells, how)

    def _lasso_catch(self) -> Any:
        """An invisible plane under the whole map that Ctrl-drags start on (viser reports
        drags on meshes, not on point clouds): the lasso's path is the pointer's."""
        xyz = np.asarray(self.map.xyz[self.map.overview], dtype=np.float64)
        low = xyz.min(axis=0) if len(xyz) else np.zeros(3)
        high = xyz.max(axis=0) if len(xyz) else np.zeros(3)
        (x0, y0), (x1, y1) = low[:2] - LASSO_MARGIN, high[:2] + LASSO_MARGIN
        z = float(low[2]) - LASSO_BELOW
        catch = self.session.client.scene.add_mesh_simple(
            f"/{self.key}/lasso_catch",
            vertices=np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32),
            faces=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
            color=(255, 255, 255), opacity=0.0, side="double", cast_shadow=False,
            receive_shadow=False,
        )  # fmt: skip
        catch.on_drag("left", modifier="cmd/ctrl")(
            lambda event: self.session.submit(self.on_lasso, event)
        )
        return catch

    def on_lasso(self, event: SceneNodeDragEvent) -> None:
        """Ctrl-drag: the free-hand lasso. Its path is drawn as it grows; at release the
        visible shown points inside it give the pillars (as the polygon's do)."""
        if event.phase == "start":
            self.lasso = [event.start_screen_pos]
            self.lasso_path = []
        self.lasso.append(event.end_screen_pos)
        self.lasso_path.append(np.asarray(event.end_position, dtype=np.float64))
        if event.phase != "end":
            now = time.perf_counter()
            if len(self.lasso_path) > 1 and now - self.lasso_drawn >= LASSO_REDRAW_S:
                self.lasso_drawn = now
                path = np.asarray(self.lasso_path)
                self._mark("lasso", np.stack([path[:-1], path[1:]], axis=1))
            return
        screen = ScreenCamera.of(self.session.client.camera)
        corners = np.asarray(self.lasso, dtype=np.float64) * (screen.width, screen.height)
        self.lasso, self.lasso_path = [], []
        self._mark("lasso", np.zeros((0, 2, 3)))
        if len(np.unique(np.round(corners), axis=0)) < 3:
            self.status.content = "Lasso dropped: draw round what you want (Ctrl-drag)."
            return
        self._select_inside(corners, screen, "lasso")

    def _measure(self, hit: np.ndarray) -> None:
        """Measure: the distance from the previous point clicked to this one."""
        self.measured.append(hit)
        if len(self.measured) == 1:
            self._mark("measure", np.zeros((0, 2, 3)))
            self.section = None
            self.status.content = "Measure: click the second point."
            return
        a, b = self.measured[-2], self.measured[-1]
        self.measured = []
        self._mark("measure", np.stack([a, b])[None])
        self.status.content = measure_text(a, b) + "; its cross-section is the side view."
        self.section = (a, b)
        self._draw_views()

    def _inspect(self, hit: np.ndarray) -> None:
        """Inspect: the point's world coordinates, height above ground, intensity, pillar and
        labels."""
        shown = self._shown()
        i = int(shown.index[np.argmin(((shown.xyz - hit) ** 2).sum(axis=1))])
        world = np.asarray(self.map.xyz[i], dtype=np.float64) + self.map.origin
        intensity = float(self.map.intensity[i])
        k = int(self.map.cell[i])
        human, model, confidence = self.view.pillar_labels(k)
        names = {-1: "none", **{int(c): n for c, n in CLASS_NAMES.items()}}
        height = float(self._height_above_ground(np.array([i]))[0])
        self.status.content = (
            f"Point x {world[0]:.2f}, y {world[1]:.2f}, z {world[2]:.2f} "
            f"({height:+.2f} m above the ground); intensity "
            f"{'n/a' if not np.isfinite(intensity) else f'{intensity:g}'}; pillar "
            f"{int(self.map.cells[k])}: human {names[human]}, model {names[model]}"
            + ("" if not np.isfinite(confidence) else f" ({confidence:.2f})")
        )

    def _rectangle_options(self) -> RectangleOptions:
        near, far = (float(v) for v in self.depth_range.value)
        return RectangleOptions(through=bool(self.through.value), near=near, far=far)

    def on_rect_select(self, event: SceneRectSelectEvent) -> None:
        """Rectangle: the pillars of the shown points inside it that are seen (or all, with
        "select hidden points too") within the depth range."""
        shown = self._shown()
        options = self._rectangle_options()
        inside = rectangle_points(
            shown.xyz, event.client.camera, event.screen_min, event.screen_max,
            float(self.point_size.value), options,
        )  # fmt: skip
        cells = self._cells_of(shown.cell[inside])
        if not len(cells):
            self.session.notify("Rectangle", "No visible points inside the rectangle.")
            return
        self._select(cells, "rectangle" + (", hidden points too" if options.through else ""))

    def _select(self, cells: np.ndarray, how: str) -> None:
        """A selection: labelled at once when small, else previewed until Enter."""
        self._drop_pending()
        if len(cells) <= CONFIRM_ABOVE:
            self._label(cells, how)
            return
        self.pending = PendingSelection(
            self.session.client.scene, f"/{self.key}/selection", cells, how
        )
        self._draw_pending()
        self.apply_selection.disabled = False
        self.cancel_selection.disabled = False
        self.status.content = (
            f"{len(cells):,} pillars selected ({how}, green): **Enter** labels them with "
            "the class chosen then, **Esc** drops the selection."
        )

    def _draw_pending(self) -> None:
        if self.pending is None:
            return
        shown = self._shown()
        k, found = self.map.cell_index(self.pending.cells)
        selected = np.zeros(len(self.map.cells), dtype=bool)  # a lookup per shown point,
        selected[k[found]] = True  # not a search: a street's fill selects 30,000 pillars
        self.pending.draw(shown.xyz[selected[shown.cell]], float(self.point_size.value))

    def _drop_pending(self) -> None:
        if self.pending is not None:
            self.pending.remove()
            self.pending = None
        if hasattr(self, "apply_selection"):
            self.apply_selection.disabled = True
            self.cancel_selection.disabled = True

    def confirm_selection(self) -> None:
        """Enter: label the previewed pillars with the class chosen now (or close the
        polygon being drawn)."""
        if self.pending is None and len(self.polygon) >= 3:
            self._close_polygon()
            return
        if self.pending is None:
            self.status.content = "No selection to apply: shift-drag a rectangle first."
            return
        pending = self.pending
        self._drop_pending()
        self._label(pending.cells, pending.how)

    def cancel_pending(self) -> None:
        """Esc: drop the previewed selection (and a polygon being drawn), nothing written."""
        if self.polygon:
            self.polygon = []
            self._mark("polygon", np.zeros((0, 2, 3)))
            self.status.content = "Polygon dropped."
        if self.pending is None:
            return
        n = len(self.pending.cells)
        self._drop_pending()
        self.status.content = f"Selection of {n:,} pillars dropped; nothing written."

    def _unlocked(self, cells: np.ndarray) -> np.ndarray:
        """The pillars "Apply to" lets a write reach: all, those without a human label, or
        those now shown as one class."""
        choice = self.apply_to.value
        if choice == APPLY_TO[0]:
            return cells
        k, found = self.map.cell_index(cells)
        cells, k = cells[found], k[found]
        human, klass = self.view.pillar_state(k)
        if choice == APPLY_TO[1]:
            return cells[human < 0]
        wanted = APPLY_TO.index(choice) - 2  # "Only <class>" in PillarClass order
        return cells[klass == wanted]

    def _label(self, cells: np.ndarray, how: str) -> None:
        cells = self._unlocked(cells)
        if not len(cells):
            self.status.content = (
                f"Nothing to label: no pillar of the {how} is {self.apply_to.value.lower()}."
            )
            return
        value = self.label_value
        try:
            result = self.session.write_pillar_labels(cells, np.full(len(cells), value))
        except StaleWriteError as exc:
            self.session.notify("Changed meanwhile", f"{exc.message} (now shown)", error=True)
            self.status.content = (
                f"Nothing written: {len(exc.current):,} of the {len(cells):,} pillars were "
                "labelled by someone else since you saw them. Their labels are shown now; "
                "label again to overwrite them."
            )
            return
        what = ERASE.lower() + "d" if value == NO_LABEL else CLASS_NAMES[PillarClass(value)]
        self.status.content = f"{len(cells):,} pillars: {what} ({how}, batch {result.batch_id})"

    def undo(self) -> None:
        result = self.session.undo_pillars()
        self.status.content = f"Undid batch {result.batch_id} ({len(result.cell_ids):,} pillars)"

    def redo(self) -> None:
        result = self.session.redo_pillars()
        self.status.content = f"Redid batch {result.batch_id} ({len(result.cell_ids):,} pillars)"

    def next_uncertain_area(self) -> None:
        """Fly to the most doubtful area not visited yet in this session (then start over)
        and outline it."""
        area_size = UNCERTAIN_AREA
        with self.session.db() as db:
            areas = uncertain_areas(db, self.view.survey_id, area_size=area_size, limit=100)
            prelabelled = not areas and sum(label_counts(db, self.view.survey_id)["model"]) > 0
        if not areas:
            self.status.content = (
                "No uncertain area: every doubtful model label is reviewed."
                if prelabelled
                else "No model pre-labels yet: run the phantom pipeline on this survey (the "
                "dashboard's survey page) and its least confident areas come up here."
            )
            return
        fresh = [a for a in areas if (a.x, a.y) not in self.visited]
        if not fresh:
            self.visited.clear()
            fresh = areas
        area = fresh[0]
        self.visited.add((area.x, area.y))
        xy = np.array([area.x, area.y]) - self.map.origin[:2]
        look_at = np.array([xy[0], xy[1], float(self.map.ground.height(xy[None])[0])])
        camera = self.session.client.camera
        offset = np.asarray(camera.position) - np.asarray(camera.look_at)
        norm = float(np.linalg.norm(offset))
        offset = offset / norm * UNCERTAIN_VIEW_DISTANCE if norm > 0 else np.array([0, -18, 18])
        self.session.move_camera(look_at, offset)
        self._focus(look_at)
        self._outline_area(look_at, area_size)
        self.status.content = (
            f"Uncertain area (red box): {area.pillars} pillars, mean confidence "
            f"{area.mean_confidence:.2f} ({len(fresh) - 1} more to visit)"
        )

    def _outline_area(self, ground_centre: np.ndarray, size: float) -> None:
        """A red wireframe box over the area flown to (replacing the previous one)."""
        if self.area_outline is not None:
            self.area_outline.remove()
        self.area_outline = self.session.client.scene.add_box(
            f"/{self.key}/uncertain_area",
            color=TARGET_RGB,
            dimensions=(size, size, AREA_HEIGHT),
            wireframe=True,
            position=tuple((ground_centre + [0.0, 0.0, AREA_HEIGHT / 2]).tolist()),
        )
