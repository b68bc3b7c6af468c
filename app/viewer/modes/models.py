"""Model inspection: the reconstructed guardrails over the points they were built from.

Each model of the survey (`GuardrailModel`) is drawn from its glTF mesh (vertices relative to the
model's origin, re-centred here on the survey origin, so nothing goes to the browser as large
float coordinates) in its review colour, over the points of its slices from the last run's slice
stage. The panel lists kind, units, ICP residual and status; a reviewer accepts or rejects the
selected guardrail (`decide_model`, with the version this client saw; stale -> reloaded). The
export link downloads the approved meshes (`/surveys/{id}/exports/guardrails.zip`). Decisions
by anyone else update the list and the mesh colours; a new run or rebuild reloads the meshes
(the selected guardrail stays selected when it survived).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh

from app.core.errors import StaleWriteError
from app.review.guardrails import load_stage
from app.store.guardrail_review import decide_model, list_models
from app.store.guardrail_runs import latest_run, match_slices
from app.store.models import GuardrailModel, ModelStatus, Role
from app.viewer.label_feed import GUARDRAIL_RUN, MODEL_DECISIONS
from app.viewer.modes.base import Mode
from app.viewer.modes.common import checked_user, evenly, legend_html, may, pick_clicked

if TYPE_CHECKING:
    from viser import SceneClickEvent

    from app.viewer.session import ViewerSession

# meshes in their review colour, the selected one also outlined in orange (its decision colour
# stays visible: a rejected model must not look like a selected one), points grey on white
MODEL_POINT_SIZE = 0.04  # metres: the guardrail points under the meshes
STATUS_RGB = {
    ModelStatus.pending: (70, 130, 230),
    ModelStatus.approved: (50, 185, 80),
    ModelStatus.rejected: (225, 50, 50),
}
SELECTED_RGB = (255, 150, 0)
POINT_RGB = np.array((150, 150, 150), dtype=np.uint8)
SELECTED_POINT_RGB = np.array((90, 90, 90), dtype=np.uint8)
VIEW_DISTANCE = 14.0  # metres from the camera to a guardrail it flies to


def load_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices relative to the origin, faces, world origin) of an exported guardrail glTF:
    the exporter stores local vertices under a node translated to the model's origin."""
    scene = trimesh.load(str(path), force="scene")
    vertices, faces, offset = [], [], 0
    origin = None
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geometry = scene.geometry[name]
        if origin is None:
            origin = np.asarray(transform[:3, 3], dtype=np.float64)
        local = geometry.vertices @ transform[:3, :3].T + (transform[:3, 3] - origin)
        vertices.append(local)
        faces.append(np.asarray(geometry.faces) + offset)
        offset += len(local)
    if origin is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(3)
    return np.concatenate(vertices), np.concatenate(faces), origin


def model_table(models: list[GuardrailModel], selected: int | None) -> str:
    """The markdown list: kind, units, ICP residual, status."""
    if not models:
        return "No guardrail was reconstructed."
    lines = ["| # | kind | units | ICP residual | status |", "|---|---|---|---|---|"]
    for m in models:
        mark = "▶ " if m.id == selected else ""
        residual = (
            "n/a"
            if m.icp_residual is None or not math.isfinite(m.icp_residual)
            else f"{m.icp_residual:.3f} m"
        )
        lines.append(
            f"| {mark}{m.guardrail_index} | {m.kind.value} | {m.unit_count} | {residual} "
            f"| {m.status.value} |"
        )
    return "\n".join(lines)


class ModelMode(Mode):
    name = "Model inspection"
    key = "models"

    def enter(self, session: ViewerSession) -> None:
        self.session = session
        self.survey_id = session.view.survey_id
        self.origin = session.view.map.origin
        self.meshes: dict[int, Any] = {}
        self.geometry: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.outline: Any = None  # the selected model's orange wireframe
        self.cloud: Any = None
        self.selected: int | None = None
        gui = session.client.gui
        with session.db() as db:
            run = latest_run(db, self.survey_id)
            self.models = list_models(db, self.survey_id)
        if run is None:
            with session.mode_folder:
                gui.add_markdown(
                    "**No guardrail run on this survey yet.** Start *run:guardrail* from the "
                    "dashboard; the guardrails it reconstructs show up here."
                )
            return
        self.reviewer = may(session, Role.reviewer)
        self._load_points(run)
        self._build_gui()
        self._draw()
        if self.models:
            self.select(self.models[0].id, fly=True)

    def leave(self) -> None:
        for mesh in self.meshes.values():
            mesh.remove()
        self.meshes = {}
        if self.outline is not None:
            self.outline.remove()
            self.outline = None
        if self.cloud is not None:
            self.cloud.remove()
            self.cloud = None

    # --- data ---------------------------------------------------------------------------------

    def _load_points(self, run: Any) -> None:
        """Each model's slice points from the run's stage (model id per shown point): the
        models' slices' points only are read."""
        s = load_stage(run, slices_only=True).slices
        model_of_slice = np.full(len(s), -1, dtype=np.int64)
        for m in self.models:  # one lookup per model, vectorised over its slices
            keys = np.asarray((m.params or {}).get("slices") or [], dtype=np.int64).reshape(-1, 2)
            at = match_slices(keys[:, 0], keys[:, 1], s.component, s.station_index)
            model_of_slice[at[at >= 0]] = m.id
        stage = load_stage(run, points_of=model_of_slice >= 0)
        s = stage.slices
        owner = np.where(s.point_slice >= 0, model_of_slice[np.maximum(s.point_slice, 0)], -1)
        cap = self.session.viewer.settings.viewer_tile_points
        self.shown = evenly(np.flatnonzero(owner >= 0), cap)
        self.point_model = owner[self.shown]
        self.xyz = (stage.xyz[self.shown] - self.origin).astype(np.float32)

    def _build_gui(self) -> None:
        session = self.session
        gui = session.client.gui
        submit = session.submit
        with session.mode_folder:
            gui.add_html(
                legend_html(
                    [(f"model: {s.value}", rgb) for s, rgb in STATUS_RGB.items()]
                    + [("selected", SELECTED_RGB), ("its slice points", POINT_RGB)]
                )
            )
            self.table = gui.add_markdown(model_table(self.models, None))
            names = tuple(self._name(m) for m in self.models) or ("(none)",)
            self.choice = gui.add_dropdown("Guardrail", names, disabled=not self.models)
            self.details = gui.add_markdown("")
            self.decision = gui.add_button_group(
                "Decision", ("Accept", "Reject"), visible=self.reviewer and bool(self.models)
            )
            fly = gui.add_button("Fly to guardrail", disabled=not self.models)
            url = f"/surveys/{self.survey_id}/exports/guardrails.zip"
            gui.add_markdown(
                f"**Export** (approved models): [guardrails.zip]({url}) "
                f"(glb), [as OBJ]({url}?format=obj)"
            )
            note = "" if self.reviewer else "Read only: accepting needs the reviewer role. "
            self.status = gui.add_markdown(note + "Click a guardrail to select it.")
        self.choice.on_update(lambda _: submit(self._chosen))
        self.decision.on_click(lambda event: submit(self._decide_selected, event.target.value))
        fly.on_click(lambda _: submit(self.fly_to_selected))

    @staticmethod
    def _name(m: GuardrailModel) -> str:
        return f"{m.guardrail_index}: {m.kind.value} (id {m.id})"

    def _model(self, model_id: int | None) -> GuardrailModel | None:
        return next((m for m in self.models if m.id == model_id), None)

    # --- drawing ------------------------------------------------------------------------------

    def _draw(self) -> None:
        scene = self.session.client.scene
        self.cloud = scene.add_point_cloud(
            f"/{self.key}/points",
            points=self.xyz,
            colors=self._point_colors(),
            point_size=MODEL_POINT_SIZE,
            precision="float32",
            point_shading="flat",
        )
        self.centres: dict[int, np.ndarray] = {}
        self.extents: dict[int, float] = {}
        for m in self.models:  # one mesh per model
            if not m.mesh_path or not Path(m.mesh_path).is_file():
                continue
            vertices, faces, origin = load_mesh(m.mesh_path)
            if not len(faces):
                continue
            position = origin - self.origin
            lo, hi = vertices.min(axis=0), vertices.max(axis=0)
            self.centres[m.id] = position + (lo + hi) / 2
            self.extents[m.id] = float(np.linalg.norm(hi - lo))
            handle = scene.add_mesh_simple(
                f"/{self.key}/mesh/{m.id}",
                vertices.astype(np.float32),
                faces.astype(np.uint32),
                color=STATUS_RGB[m.status],
                position=tuple(position.tolist()),
                flat_shading=False,
                side="double",
            )
            handle.on_click(lambda _, i=m.id: self.session.submit(self.select, i))
            self.meshes[m.id] = handle
            self.geometry[m.id] = (vertices.astype(np.float32), faces.astype(np.uint32), position)

    def _outline(self) -> None:
        """An orange wireframe over the selected model (its mesh keeps its decision colour)."""
        name = f"/{self.key}/selected/{self.selected}"
        if self.outline is not None and self.outline.name != name:
            self.outline.remove()
            self.outline = None
        if self.outline is not None or self.selected not in self.geometry:
            return
        vertices, faces, position = self.geometry[self.selected]
        self.outline = self.session.client.scene.add_mesh_simple(
            name,
            vertices,
            faces,
            color=SELECTED_RGB,
            wireframe=True,
            position=tuple(position.tolist()),
        )

    def _point_colors(self) -> np.ndarray:
        rgb = np.tile(POINT_RGB, (len(self.point_model), 1))
        if self.selected is not None:
            rgb[self.point_model == self.selected] = SELECTED_POINT_RGB
        return rgb

    def _recolor(self) -> None:
        for m in self.models:
            handle = self.meshes.get(m.id)
            if handle is not None:
                handle.color = STATUS_RGB[m.status]
        self._outline()
        if self.cloud is not None:
            self.cloud.colors = self._point_colors()
        self.table.content = model_table(self.models, self.selected)
        m = self._model(self.selected)
        if m is None:
            self.details.content = ""
        else:
            p = m.params or {}
            span = p.get("station_m") or [math.nan, math.nan]
            who = "" if m.decided_by is None else f" by user {m.decided_by}"
            unit = p.get("unit_length")
            self.details.content = (
                f"**{m.kind.value} {m.guardrail_index}**: {m.unit_count} units"
                + ("" if unit is None else f" of {unit:.2f} m")
                + f", {len(p.get('poles') or [])} poles, stations {span[0]:.1f}-{span[1]:.1f} m; "
                f"**{m.status.value}**{who} (version {m.version}). "
                f"[mesh (glb)](/surveys/{self.survey_id}/guardrails/models/{m.id}/mesh)"
            )
        self.session.client.flush()

    # --- actions ------------------------------------------------------------------------------

    def _chosen(self) -> None:
        m = next((m for m in self.models if self._name(m) == self.choice.value), None)
        if m is not None and m.id != self.selected:
            self.select(m.id, fly=True)

    def select(self, model_id: int, fly: bool = False) -> None:
        m = self._model(model_id)
        if m is None:
            return
        self.selected = model_id
        if self.choice.value != self._name(m):
            self.choice.value = self._name(m)
        if fly:
            self.fly_to_selected()
        self._recolor()

    def fly_to_selected(self) -> None:
        centre = self.centres.get(self.selected) if self.selected is not None else None
        if centre is None:
            return
        camera = self.session.client.camera
        offset = np.asarray(camera.position) - np.asarray(camera.look_at)
        norm = float(np.linalg.norm(offset))
        distance = max(VIEW_DISTANCE, 0.9 * self.extents.get(self.selected, 0.0))  # all of it
        offset = offset / norm * distance if norm > 0 else np.array([-0.6, -0.6, 0.6]) * distance
        self.session.move_camera(centre, offset)

    def on_click(self, event: SceneClickEvent) -> None:
        """Select the guardrail whose slice point lies nearest along the click ray."""
        if self.cloud is None:
            return
        hit = pick_clicked(self.xyz, event, MODEL_POINT_SIZE)
        if hit >= 0:
            self.select(int(self.point_model[hit]))

    def _decide_selected(self, action: str) -> None:
        status = ModelStatus.approved if action == "Accept" else ModelStatus.rejected
        self.decide(self.selected, status)

    def decide(self, model_id: int | None, status: ModelStatus) -> None:
        """Accept / reject through the store with the version we hold; stale -> reload."""
        m = self._model(model_id)
        if m is None:
            self.status.content = "Select a guardrail first."
            return
        user = checked_user(self.session, Role.reviewer, "deciding on guardrail models")
        try:
            with self.session.db() as db:
                row = decide_model(db, self.survey_id, m.id, m.version, status, user)
            self.session.viewer.labels_written()  # other clients follow now
        except StaleWriteError as exc:
            self.session.notify("Changed meanwhile", f"{exc.message} (reloaded)", error=True)
            self.status.content = "Someone else decided first: the list was reloaded."
            self.reload()
            return
        self.models = [row if x.id == row.id else x for x in self.models]
        self.status.content = f"Guardrail {row.guardrail_index} {row.status.value}."
        self._recolor()

    def on_review_changed(self, actions: set[str]) -> None:
        """Model decisions by anyone: re-read the list; a new run or rebuild: reload."""
        if actions & GUARDRAIL_RUN:
            selected = getattr(self, "selected", None)
            mode = self.session.reload_mode()
            shown = isinstance(mode, ModelMode) and getattr(mode, "choice", None) is not None
            if shown and mode._model(selected) is not None:
                mode.select(selected)
        elif actions & MODEL_DECISIONS and getattr(self, "table", None) is not None:
            self.reload()

    def reload(self) -> None:
        with self.session.db() as db:
            self.models = list_models(db, self.survey_id)
        self._recolor()
