"""Guardrail review: correct the 0.5 m slice labels the guardrail run predicted.

The points of every slice come from the slice stage the last `run:guardrail` saved
(`ReconstructionInput`, found through the store's ingest event); they are re-centred on the
survey origin and coloured by the slice's current label in the store: guardrail or other,
brighter where a person labelled the slice, darker where the label is still the classifier's
(after adjacency correction). A click toggles the slice nearest the cursor (one versioned write
through `app.store.guardrail_review.put_slice_labels`, as this session's user); "Next uncertain
slice" flies to the unlabelled slice whose probability is nearest 0.5. The slice last clicked or
flown to is the selected one: its points drawn large in their label's colour inside a red box,
so the target is seen and its label stays readable; "Preview correction" colours the
slices the adjacency correction would change (`preview_correction`, nothing saved) and "Apply"
writes those as human labels in one batch. Labels written by anyone else recolour the slices
(and drop a preview computed before them); a new run or rebuild reloads the mode.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from app.core.errors import StaleWriteError
from app.review.guardrails import preview_correction, stage_sample
from app.store.guardrail_review import (
    MAX_LABELS_PER_WRITE,
    SliceLabelEdit,
    next_uncertain,
    put_slice_labels,
    review_slice_rows,
)
from app.store.guardrail_runs import latest_run, match_slices
from app.store.models import GuardrailSlice, Role
from app.viewer.label_feed import GUARDRAIL_RUN, SLICE_LABEL
from app.viewer.modes.base import Mode
from app.viewer.modes.common import (
    TARGET_RGB,
    checked_user,
    evenly,
    legend_html,
    may,
    pick_clicked,
)

if TYPE_CHECKING:
    from viser import SceneClickEvent

    from app.viewer.session import ViewerSession

# slice colours: [label, human]; slices the store does not know are grey
LABEL_RGB = np.array(
    [
        [(70, 95, 130), (40, 130, 255)],  # other: classifier (dark), human (bright)
        [(150, 105, 40), (255, 160, 0)],  # guardrail: classifier (dark), human (bright)
    ],
    dtype=np.uint8,
)
UNKNOWN_RGB = np.array((110, 110, 110), dtype=np.uint8)
PREVIEW_RGB = {1: np.array((235, 40, 210), np.uint8), 0: np.array((0, 225, 225), np.uint8)}
FOCUS_BOX_RGB = TARGET_RGB  # the selected slice's box: red, no label colour
FOCUS_SCALE = 2.5  # the selected slice's points are drawn this much larger
FOCUS_PAD = 0.25  # metres around the selected slice's points
MAP_RGB = np.array((70, 70, 70), dtype=np.uint8)
MAP_POINTS = 100_000  # most context points of the survey's map under the slices
VIEW_DISTANCE = 12.0  # metres from the camera to a slice it flies to


class SliceRows:
    """The survey's slices in the store as arrays (id order), with versions for writes."""

    def __init__(self, rows: list[tuple]):
        a = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
        self.id = a[:, 0].astype(np.int64)
        self.component = a[:, 1].astype(np.int64)
        self.slice_index = a[:, 2].astype(np.int64)
        self.label = a[:, 3].astype(np.int64)
        self.human = a[:, 4].astype(bool)
        self.version = a[:, 5].astype(np.int64)
        self.probability = a[:, 6]  # nan: none

    def __len__(self) -> int:
        return len(self.id)

    def update(self, rows: list[GuardrailSlice]) -> None:
        """Take the store's answer to a write (label, labeller, version) for these slices."""
        ids = np.array([r.id for r in rows], dtype=np.int64)
        at = np.searchsorted(self.id, ids)
        self.label[at] = [r.label for r in rows]
        self.human[at] = [r.labelled_by is not None for r in rows]
        self.version[at] = [r.version for r in rows]


def read_slices(session: ViewerSession, survey_id: int) -> SliceRows:
    with session.db() as db:
        rows = review_slice_rows(db, survey_id)
    return SliceRows([tuple(np.nan if v is None else v for v in r) for r in rows])


def slice_colors(
    row_of_slice: np.ndarray,
    rows: SliceRows,
    preview: dict[int, int] | None = None,
) -> np.ndarray:
    """(K, 3) colour per stage slice: current label (human brighter), preview overlay (the
    label the correction would give, where it differs)."""
    known = row_of_slice >= 0
    rgb = np.tile(UNKNOWN_RGB, (len(row_of_slice), 1))
    r = row_of_slice[known]
    rgb[known] = LABEL_RGB[rows.label[r], rows.human[r].astype(np.int64)]
    if preview:
        ids = np.fromiter(preview.keys(), dtype=np.int64, count=len(preview))
        to = np.fromiter(preview.values(), dtype=np.int64, count=len(preview))
        slice_of_row = np.full(len(rows), -1, dtype=np.int64)
        slice_of_row[row_of_slice[known]] = np.flatnonzero(known)
        k = slice_of_row[np.searchsorted(rows.id, ids)]
        for label, colour in PREVIEW_RGB.items():
            pick = k[(to == label) & (k >= 0)]
            rgb[pick] = colour
    return rgb


class GuardrailMode(Mode):
    name = "Guardrail review"
    key = "guardrails"

    def enter(self, session: ViewerSession) -> None:
        self.session = session
        self.survey_id = session.view.survey_id
        self.origin = session.view.map.origin
        self.clouds: dict[str, Any] = {}
        self.preview: dict[int, int] = {}  # slice id -> corrected label, where it differs
        self.focus: int | None = None  # the selected stage slice (clicked or flown to)
        self.focus_nodes: list[Any] = []
        gui = session.client.gui
        with session.db() as db:
            run = latest_run(db, self.survey_id)
        if run is None:
            with session.mode_folder:
                gui.add_markdown(
                    "**No guardrail run on this survey yet.** Start *run:guardrail* from the "
                    "dashboard; its slices show up here for review when it has finished."
                )
            return
        cap = session.viewer.settings.viewer_tile_points
        self.stage, xyz, self.point_slice = stage_sample(run, cap)  # slices; `cap` points
        s = self.stage.slices
        self.rows = read_slices(session, self.survey_id)
        self.row_of_slice = match_slices(
            s.component, s.station_index, self.rows.component, self.rows.slice_index
        )
        self.xyz = (xyz - self.origin).astype(np.float32)
        self.shown = np.arange(len(self.xyz))
        self.annotator = may(session, Role.annotator)
        self._build_gui()
        self._draw()
        self._describe()

    def leave(self) -> None:
        for cloud in self.clouds.values():
            cloud.remove()
        self.clouds = {}
        self._remove_focus()
        command = getattr(self, "command", None)
        if command is not None:
            command.remove()
            self.command = None

    # --- GUI ----------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        session = self.session
        gui = session.client.gui
        submit = session.submit
        with session.mode_folder:
            gui.add_html(
                legend_html(
                    [
                        ("guardrail (human)", LABEL_RGB[1, 1]),
                        ("guardrail (classifier)", LABEL_RGB[1, 0]),
                        ("other (human)", LABEL_RGB[0, 1]),
                        ("other (classifier)", LABEL_RGB[0, 0]),
                        ("preview: would become guardrail", PREVIEW_RGB[1]),
                        ("preview: would become other", PREVIEW_RGB[0]),
                        ("selected slice: large points in a red box", FOCUS_BOX_RGB),
                    ]
                )
            )
            self.summary = gui.add_markdown("")
            jump = gui.add_button("Next uncertain slice", hint="N: unlabelled, probability ~0.5")
            preview = gui.add_button("Preview correction", hint="the adjacency correction, unsaved")
            self.apply = gui.add_button(
                "Apply correction", disabled=True, hint="write the previewed labels as yours"
            )
            clear = gui.add_button("Clear preview")
            with gui.add_folder("Display", expand_by_default=False):
                self.show_map = gui.add_checkbox("Show the map", initial_value=True)
                self.point_size = gui.add_slider(
                    "Point size", min=0.01, max=0.3, step=0.01, initial_value=0.05
                )
            note = "" if self.annotator else "Read only: labelling needs the annotator role. "
            self.status = gui.add_markdown(note + "Click a slice to toggle guardrail / other.")
        jump.on_click(lambda _: submit(self.next_uncertain_slice))
        preview.on_click(lambda _: submit(self.preview_correction))
        self.apply.on_click(lambda _: submit(self.apply_correction))
        clear.on_click(lambda _: submit(self.clear_preview))
        self.show_map.on_update(lambda _: submit(self._toggle_map))
        self.point_size.on_update(lambda _: submit(self._resize))
        self.command = session.client.gui.add_command("Next uncertain slice", hotkey="N")
        self.command.on_trigger(lambda _: submit(self.next_uncertain_slice))

    def _describe(self) -> None:
        rows = self.rows
        self.summary.content = (
            f"{len(rows):,} slices: {int(rows.label.sum()):,} guardrail, "
            f"{int(rows.human.sum()):,} labelled by people"
        )

    # --- drawing ------------------------------------------------------------------------------

    def _colors(self) -> np.ndarray:
        per_slice = slice_colors(self.row_of_slice, self.rows, self.preview)
        return per_slice[self.point_slice[self.shown]]

    def _draw(self) -> None:
        if self.show_map.value:
            self._draw_map()
        self.clouds["slices"] = self.session.client.scene.add_point_cloud(
            f"/{self.key}/slices",
            points=self.xyz[self.shown],
            colors=self._colors(),
            point_size=self.point_size.value,
            precision="float32",
            point_shading="flat",
        )
        if len(self.shown):  # look at the slices from behind-left and above
            lo, hi = self.xyz[self.shown].min(axis=0), self.xyz[self.shown].max(axis=0)
            distance = float(np.clip(0.6 * np.max(hi[:2] - lo[:2]), 15.0, 120.0))
            offset = np.array([-0.45, -0.55, 0.7])
            self.session.move_camera((lo + hi) / 2.0, offset / np.linalg.norm(offset) * distance)

    def _recolor(self) -> None:
        self.clouds["slices"].colors = self._colors()
        self._draw_focus()
        self._describe()
        self.session.client.flush()

    def _toggle_map(self) -> None:
        if self.show_map.value:
            self._draw_map()
        else:
            cloud = self.clouds.pop("map", None)
            if cloud is not None:
                cloud.remove()

    def _draw_map(self) -> None:
        view_map = self.session.view.map
        if "map" in self.clouds or not len(view_map):
            return
        context = evenly(view_map.overview, MAP_POINTS)
        self.clouds["map"] = self.session.client.scene.add_point_cloud(
            f"/{self.key}/map",
            points=view_map.xyz[context],
            colors=MAP_RGB,
            point_size=0.6 * self.point_size.value,
            precision="float32",
            point_shading="flat",
        )

    def _resize(self) -> None:
        for name, cloud in self.clouds.items():
            cloud.point_size = self.point_size.value * (0.6 if name == "map" else 1.0)
        if self.focus_nodes:
            self.focus_nodes[0].point_size = FOCUS_SCALE * self.point_size.value

    def _remove_focus(self) -> None:
        for node in self.focus_nodes:
            node.remove()
        self.focus_nodes = []

    def _draw_focus(self) -> None:
        """The selected slice: its points large, in their current colour, in a red box."""
        self._remove_focus()
        if self.focus is None:
            return
        mine = self.point_slice[self.shown] == self.focus
        if not mine.any():
            return
        xyz = self.xyz[self.shown[mine]]
        scene = self.session.client.scene
        cloud = scene.add_point_cloud(
            f"/{self.key}/selected/points",
            points=xyz,
            colors=self._colors()[mine],
            point_size=FOCUS_SCALE * self.point_size.value,
            precision="float32",
            point_shading="flat",
        )
        lo, hi = xyz.min(axis=0) - FOCUS_PAD, xyz.max(axis=0) + FOCUS_PAD
        box = scene.add_box(
            f"/{self.key}/selected/box",
            color=FOCUS_BOX_RGB,
            dimensions=tuple((hi - lo).astype(float).tolist()),
            wireframe=True,
            position=tuple(((lo + hi) / 2.0).astype(float).tolist()),
        )
        self.focus_nodes = [cloud, box]

    # --- actions ------------------------------------------------------------------------------

    def on_review_changed(self, actions: set[str]) -> None:
        """Slice labels by anyone: re-read and recolour; a new run or rebuild: reload."""
        if actions & GUARDRAIL_RUN:
            self.session.reload_mode()
            return
        if SLICE_LABEL not in actions or "slices" not in self.clouds:
            return
        before = self.rows
        self._reload()
        same = np.array_equal(before.id, self.rows.id) and np.array_equal(
            before.version, self.rows.version
        )
        if same:  # our own writes (already applied) or nothing of ours
            return
        if self.preview:  # computed from labels that changed since
            self.preview = {}
            self.apply.disabled = True
            self.apply.label = "Apply correction"
            self.status.content = "Someone else labelled slices: preview cleared, preview again."
        self._recolor()

    def _reload(self) -> None:
        self.rows = read_slices(self.session, self.survey_id)
        s = self.stage.slices
        self.row_of_slice = match_slices(
            s.component, s.station_index, self.rows.component, self.rows.slice_index
        )

    def _write(self, edits: list[SliceLabelEdit]) -> bool:
        """Versioned label writes (batches of the store's maximum); stale -> reload, False."""
        user = checked_user(self.session, Role.annotator, "labelling guardrail slices")
        try:
            for start in range(0, len(edits), MAX_LABELS_PER_WRITE):
                with self.session.db() as db:
                    written = put_slice_labels(
                        db, self.survey_id, edits[start : start + MAX_LABELS_PER_WRITE], user
                    )
                self.rows.update(written)
                self.session.viewer.labels_written()  # other clients follow now
        except StaleWriteError as exc:
            self.session.notify("Changed meanwhile", f"{exc.message} (reloaded)", error=True)
            self.status.content = "Someone else labelled these slices first: reloaded."
            self._reload()
            self._recolor()
            return False
        return True

    def on_click(self, event: SceneClickEvent) -> None:
        """Toggle the label of the clicked slice (the nearest slice point along the ray)."""
        if "slices" not in self.clouds:
            return
        hit = pick_clicked(self.xyz[self.shown], event, self.point_size.value)
        if hit < 0:
            self.status.content = "No slice under the click."
            return
        self.toggle_slice(int(self.point_slice[self.shown[hit]]))

    def toggle_slice(self, k: int) -> None:
        """Stage slice k: guardrail <-> other, as a human label at the version we hold."""
        r = int(self.row_of_slice[k])
        if r < 0:
            self.status.content = "This slice is not in the store any more: run guardrail again."
            return
        new = 1 - int(self.rows.label[r])
        edit = SliceLabelEdit(int(self.rows.id[r]), int(self.rows.version[r]), new)
        self.focus = k
        if self._write([edit]):
            what = "guardrail" if new else "other"
            self.status.content = f"Slice {edit.id} is now **{what}** (version {edit.version + 1})."
            self._drop_stale_preview()
            self._recolor()

    def next_uncertain_slice(self) -> None:
        """Fly to the unlabelled slice whose probability is nearest 0.5."""
        self._reload()
        with self.session.db() as db:
            row, remaining = next_uncertain(db, self.survey_id)
        if row is None:
            self.focus = None
            self.status.content = "Every slice has a human label."
            self._recolor()
            return
        s = self.stage.slices
        at = match_slices([row.component_id], [row.slice_index], s.component, s.station_index)
        k = int(at[0])
        self.focus = k if k >= 0 else None
        if k >= 0:
            look_at = self._anchor(k)
            camera = self.session.client.camera
            offset = np.asarray(camera.position) - np.asarray(camera.look_at)
            norm = float(np.linalg.norm(offset))
            offset = offset / norm * VIEW_DISTANCE if norm > 0 else np.array([-6.0, -6.0, 8.0])
            self.session.move_camera(look_at, offset)
        p = "n/a" if row.probability is None else f"{row.probability:.2f}"
        self.status.content = (
            f"Slice {row.id} (component {row.component_id}, #{row.slice_index}, "
            f"{row.station_m:.1f} m): probability {p}; {remaining:,} unlabelled left."
        )
        self._recolor()

    def _anchor(self, k: int) -> np.ndarray:
        """Where to look at slice k: its shown point nearest its centre (the centre is a mean
        and may lie in the air between a rail and a post, where a click meets another slice),
        the centre when none of its points is shown."""
        centre = self.stage.slices.centre[k] - self.origin
        mine = self.shown[self.point_slice[self.shown] == k]
        if not len(mine):
            return centre
        xyz = self.xyz[mine].astype(np.float64)
        return xyz[int(np.argmin(((xyz - centre) ** 2).sum(axis=1)))]

    def preview_correction(self) -> None:
        """Colour the slices whose label the adjacency correction would change."""
        self._reload()
        with self.session.db() as db:
            result = preview_correction(db, self.survey_id, {})
        self.preview = {
            s["id"]: s["corrected_label"]
            for s in result["slices"]
            if s["corrected_label"] != s["label"]
        }
        n = len(self.preview)
        self.apply.disabled = n == 0 or not self.annotator
        self.apply.label = f"Apply correction ({n} slices)" if n else "Apply correction"
        self.status.content = (
            f"Correction (gap {result['max_gap']}, isolated {result['max_isolated']}) would "
            f"change {n} slice(s); {result['guardrail_slices']:,} guardrail slices after it."
        )
        self._recolor()

    def apply_correction(self) -> None:
        """Write the previewed labels as this user's labels (one batch)."""
        if not self.preview:
            self.status.content = "No preview to apply."
            return
        at = np.searchsorted(self.rows.id, np.fromiter(self.preview, dtype=np.int64))
        edits = [
            SliceLabelEdit(int(self.rows.id[r]), int(self.rows.version[r]), label)
            for r, label in zip(at.tolist(), self.preview.values(), strict=True)
        ]
        if self._write(edits):
            self.status.content = f"Applied the correction to {len(edits)} slice(s)."
        self.clear_preview()

    def clear_preview(self) -> None:
        self.preview = {}
        self.apply.disabled = True
        self.apply.label = "Apply correction"
        self._recolor()

    def _drop_stale_preview(self) -> None:
        """A toggled slice invalidates the preview (it was computed from other labels)."""
        if self.preview:
            self.preview = {}
            self.apply.disabled = True
            self.apply.label = "Apply correction"
            self.status.content += " Preview cleared: preview again."
