"""QA: what the cleaning did to the map, and how well the pipelines scored.

The newest succeeded job of a pipeline that removes points (`run:clutter`, `clutter:recompute`,
`run:phantom`) left the cleaned map and the removed points as LAZ files (world coordinates); both
are read once, re-centred on the survey origin and thinned to the viewer's point budget.
"Original" shows both (the removed points red when highlighted), "Cleaned" only what the map
keeps. The panel holds the paper metrics those jobs
recorded (clutter: overall accuracy, omission / commission, SA / DA / AA; phantom: per-class
precision / recall / F) and links to the exports. When such a job succeeds (the label feed's
`job.succeeded:<kind>`), the mode reloads with its maps and metrics.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.geometry.voxels import voxel_downsample
from app.io.las import read_las_points
from app.store.models import Job
from app.store.surveys import latest_succeeded_job
from app.viewer.label_feed import job_succeeded
from app.viewer.modes.base import Mode
from app.viewer.modes.common import evenly, legend_html

if TYPE_CHECKING:
    from app.viewer.session import ViewerSession

CLUTTER_KINDS = ("run:clutter", "clutter:recompute")
PHANTOM_KINDS = ("run:phantom",)
SHOWN_JOBS = frozenset(job_succeeded(kind) for kind in (*CLUTTER_KINDS, *PHANTOM_KINDS))
VOXEL = 0.1  # metres: one point per voxel before the point budget applies
REMOVED_RGB = np.array((235, 30, 30), dtype=np.uint8)
ORIGINAL, CLEANED = "Original", "Cleaned"
SCOPES = {"in_view": "camera view", "full": "360°"}


def percent(value: Any) -> str:
    """A score as the reports give it (percent); undefined (NaN) as n/a, missing as blank."""
    if value is None:
        return ""
    if isinstance(value, float) and not math.isfinite(value):
        return "n/a"
    return f"{value:.1f}" if isinstance(value, float) else str(value)


CLUTTER_ROWS = (  # (row name, part of the metrics entry, key)
    ("OA", "error_matrix", "overall_accuracy"),
    ("omission", "error_matrix", "clutter_omission"),
    ("commission", "error_matrix", "clutter_commission"),
    ("SA", "scores", "SA"),
    ("DA", "scores", "DA"),
    ("AA", "scores", "AA"),
)


def clutter_markdown(metrics: Mapping[str, Any] | None) -> str:
    """Lee et al.'s scores, one narrow table per scope (camera view / full 360; the panel is
    narrow: a wide table ran off its edge): a row per score (overall accuracy, clutter
    omission / commission, SA / DA / AA), a column per reference (dynamic / clutter classes)."""
    if not isinstance(metrics, Mapping) or not metrics:
        return "_No clutter metrics: the survey has no reference labels._"
    tables = []
    for scope, by_kind in metrics.items():
        if not isinstance(by_kind, Mapping):
            continue
        kinds = {k: e for k, e in by_kind.items() if isinstance(e, Mapping)}
        if not kinds:
            continue
        where = SCOPES.get(scope, scope.replace("_", " "))
        lines = [f"| {where} | {' | '.join(kinds)} |", "|---" + "|---:" * len(kinds) + "|"]
        for name, part, key in CLUTTER_ROWS:
            values = [(entry.get(part) or {}).get(key) for entry in kinds.values()]
            lines.append(f"| {name} | {' | '.join(map(percent, values))} |")
        tables.append("\n".join(lines))
    note = "(percent; omission / commission of the clutter points)"
    return "\n\n".join([*tables, note])


def phantom_markdown(metrics: Mapping[str, Any] | None) -> str:
    """Nagy & Benedek's per-class precision / recall / F at pillar and point level."""
    if not isinstance(metrics, Mapping) or not metrics:
        return "_No phantom metrics: no run, or no reference labels._"
    parts = []
    for key, title in (("pillar", "pillars (after the vote)"), ("point", "points")):
        scores = metrics.get(key)
        if not isinstance(scores, Mapping):
            continue
        classes = scores.get("classes") or {}
        lines = [f"**{title}**", "", "| class | P | R | F |", "|---|---:|---:|---:|"]
        for name in scores.get("names") or list(classes):
            c = classes.get(name) or {}
            lines.append(
                f"| {name} | {percent(c.get('precision'))} | {percent(c.get('recall'))} "
                f"| {percent(c.get('f1'))} |"
            )
        macro = scores.get("macro")
        if isinstance(macro, Mapping):
            lines.append(
                f"| overall | {percent(macro.get('precision'))} | "
                f"{percent(macro.get('recall'))} | {percent(macro.get('f1'))} |"
            )
        parts.append("\n".join(lines))
    return "\n\n".join(parts) or "_No phantom metrics in the last run._"


def job_path(jobs_dir: Path, job: Job, where: str) -> Path:
    """A path of a job's result: absolute as written, else relative to the job's folder."""
    path = Path(where)
    return path if path.is_absolute() else jobs_dir / str(job.id) / path


def shading_value(xyz: np.ndarray, intensity: np.ndarray | None) -> np.ndarray:
    """What the kept points are shaded by: intensity when the file has it, else height."""
    if intensity is not None and len(intensity) and np.ptp(intensity) > 0:
        return np.asarray(intensity, dtype=np.float64)
    return xyz[:, 2].astype(np.float64)


def shading(value: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(n, 3) uint8 grey of `value` between lo and hi (one range for both maps, so a removed
    point that is not highlighted looks like the map around it); dark to mid grey, never near
    white: the viewer's background is white and light points washed real scans out."""
    grey = 40 + 150 * np.clip((value - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    return np.clip(np.stack([grey, grey, grey * 1.05], axis=1), 0, 255).astype(np.uint8)


class QAMode(Mode):
    name = "QA"
    key = "qa"

    def enter(self, session: ViewerSession) -> None:
        self.session = session
        self.survey_id = session.view.survey_id
        self.origin = session.view.map.origin
        self.clouds: dict[str, Any] = {}
        settings = session.viewer.settings
        with session.db() as db:
            clutter = latest_succeeded_job(db, self.survey_id, CLUTTER_KINDS)
            phantom = latest_succeeded_job(db, self.survey_id, PHANTOM_KINDS)
            # the maps shown: the newest run of either pipeline that removes points
            remover = latest_succeeded_job(db, self.survey_id, (*CLUTTER_KINDS, *PHANTOM_KINDS))
        gui = session.client.gui
        base = f"/surveys/{self.survey_id}/exports"
        with session.mode_folder:
            if remover is None:
                gui.add_markdown(
                    "**No clutter or phantom run on this survey yet.** Start *run:clutter* or "
                    "*run:phantom* from the dashboard to compare the original and the cleaned "
                    "map here."
                )
            else:
                gui.add_markdown(
                    f"Maps from **{remover.kind}**, job {remover.id} (the newest run)."
                )
                self.show = gui.add_dropdown("Show", (ORIGINAL, CLEANED))
                self.highlight = gui.add_checkbox("Highlight removed (red)", initial_value=True)
                self.point_size = gui.add_slider(
                    "Point size", min=0.01, max=0.3, step=0.01, initial_value=0.05
                )
                gui.add_html(legend_html([("removed by cleaning", REMOVED_RGB)]))
                self.counts = gui.add_markdown("")
            with gui.add_folder("Metrics"):
                gui.add_markdown(self._clutter_text(clutter))
                gui.add_markdown(self._phantom_text(phantom))
            gui.add_markdown(
                f"**Exports**: [QA report]({base}/qa-report.html)"
                + (
                    ""
                    if remover is None
                    else f", [cleaned.laz]({base}/cleaned.laz), [removed.laz]({base}/removed.laz)"
                )
            )
        if remover is None:
            return
        self._load(remover, settings.jobs_dir, settings)
        submit = session.submit
        self.show.on_update(lambda _: submit(self._apply_view))
        self.highlight.on_update(lambda _: submit(self._recolor))
        self.point_size.on_update(lambda _: submit(self._resize))

    def on_review_changed(self, actions: set[str]) -> None:
        """A clutter or phantom job succeeded on the survey: show its maps and metrics."""
        if actions & SHOWN_JOBS:
            self.session.reload_mode()

    def leave(self) -> None:
        for cloud in self.clouds.values():
            cloud.remove()
        self.clouds = {}

    # --- panel --------------------------------------------------------------------------------

    @staticmethod
    def _clutter_text(job: Job | None) -> str:
        if job is None:
            return "**Clutter**: no finished run."
        result = job.result or {}
        counts = result.get("counts") or {}
        removed, total = counts.get("removed_points"), counts.get("points")
        share = f"{removed:,} of {total:,} points removed. " if removed and total else ""
        return f"**Clutter** (job {job.id}, {job.kind}): {share}\n\n" + clutter_markdown(
            result.get("metrics")
        )

    @staticmethod
    def _phantom_text(job: Job | None) -> str:
        if job is None:
            return "**Phantom**: no finished run."
        metrics = (job.result or {}).get("metrics")
        return f"**Phantom** (job {job.id}):\n\n" + phantom_markdown(metrics)

    # --- the maps -----------------------------------------------------------------------------

    def _read(self, path: Path, cap: int) -> tuple[np.ndarray, np.ndarray | None, int]:
        """(local float32 xyz, intensity, points in the file) thinned to `cap` points."""
        if not path.is_file():
            return np.zeros((0, 3), np.float32), None, 0
        cloud = read_las_points(path)
        xyz = (cloud.xyz - self.origin).astype(np.float32)
        keep = voxel_downsample(xyz, VOXEL) if len(xyz) else np.zeros(0, np.int64)
        keep = evenly(np.sort(keep), cap)
        intensity = None if cloud.intensity is None else cloud.intensity[keep]
        return xyz[keep], intensity, len(xyz)

    def _load(self, job: Job, jobs_dir: Path, settings: Any) -> None:
        files = (job.result or {}).get("files") or {}
        budget = settings.viewer_overview_points
        cleaned, intensity, n_cleaned = self._read(
            job_path(jobs_dir, job, files.get("cleaned", "cleaned.laz")), budget
        )
        removed, removed_intensity, n_removed = self._read(
            job_path(jobs_dir, job, files.get("removed", "removed.laz")),
            settings.viewer_tile_points,
        )
        self.removed_xyz = removed
        value = shading_value(cleaned, intensity)
        self.removed_value = shading_value(removed, removed_intensity)
        both = np.concatenate([value, self.removed_value])  # one writer: the same units
        self.shade_range = (
            tuple(float(v) for v in np.percentile(both, [2, 98])) if len(both) else (0.0, 1.0)
        )
        self.cleaned_rgb = shading(value, *self.shade_range)
        scene = self.session.client.scene
        self.clouds["cleaned"] = scene.add_point_cloud(
            f"/{self.key}/cleaned",
            points=cleaned,
            colors=self.cleaned_rgb,
            point_size=self.point_size.value,
            precision="float32",
            point_shading="flat",
        )
        self.clouds["removed"] = scene.add_point_cloud(
            f"/{self.key}/removed",
            points=removed,
            colors=self._removed_colors(),
            point_size=self.point_size.value,
            precision="float32",
            point_shading="flat",
        )
        self.counts.content = (
            f"Cleaned map: {n_cleaned:,} points; removed: {n_removed:,} points "
            f"(shown: {len(cleaned):,} + {len(removed):,})."
        )
        self._apply_view()

    def _removed_colors(self) -> np.ndarray:
        if self.highlight.value or not len(self.removed_xyz):
            return np.tile(REMOVED_RGB, (len(self.removed_xyz), 1))
        return shading(self.removed_value, *self.shade_range)

    def _apply_view(self) -> None:
        self.clouds["removed"].visible = self.show.value == ORIGINAL
        self.session.client.flush()

    def _recolor(self) -> None:
        self.clouds["removed"].colors = self._removed_colors()
        self.session.client.flush()

    def _resize(self) -> None:
        for cloud in self.clouds.values():
            cloud.point_size = self.point_size.value
