"""The QA report of one survey: a single self-contained HTML page (plots embedded as PNG data
URIs) that a reviewer can mail or archive without the server.

It holds the survey summary, the paper metrics of the newest finished run of each pipeline as
its report.json recorded them (clutter: Lee et al.'s error matrix, omission / commission and
SA / DA / AA; phantom: Nagy & Benedek's confusion matrix and per-class precision / recall / F;
guardrail: Matsumoto et al.'s slice precision / recall / F), and the review state (human labels
per class and user, clutter decisions, guardrail model verdicts).
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from datetime import UTC, datetime
from html import escape
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from sqlmodel import Session

from app.core.labels import PILLAR_CLASS_NAMES, PillarClass
from app.core.settings import Settings
from app.metrics.plots import bar_image, confusion_image
from app.store.models import Decision, Job, LabelSource, ModelStatus, Survey
from app.store.review_counts import (
    clutter_decision_counts,
    clutter_instance_count,
    guardrail_status_counts,
    pillar_label_counts,
)
from app.store.surveys import frames_summary, latest_succeeded_job

PIPELINE_JOBS: dict[str, tuple[str, ...]] = {
    "clutter": ("run:clutter", "clutter:recompute"),
    "phantom": ("run:phantom",),
    "guardrail": ("run:guardrail",),
}
PILLAR_NAMES = list(PILLAR_CLASS_NAMES)

_STYLE = """
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1100px;color:#222}
h1{margin-bottom:.2em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th:first-child,td:first-child{text-align:left}th{background:#f2f2f2}
.note{color:#666}img{max-width:100%;margin:.4em 1em .4em 0;vertical-align:top}
"""


# --- formatting ---------------------------------------------------------------------------


def job_file(settings: Settings, job: Job, path: str) -> Path:
    """A path from a job's result: absolute as written, or relative to the job's folder."""
    p = Path(path)
    return p if p.is_absolute() else settings.jobs_dir / str(job.id) / p


def number(value: Any, digits: int = 1) -> str:
    """Percentages and scores with `digits` decimals, counts with separators; NaN (undefined,
    e.g. DA without moving points) as n/a, None (not applicable) as an empty cell."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return "n/a" if not math.isfinite(value) else f"{value:,.{digits}f}"
    return str(value)


def table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    head = "".join(f"<th>{escape(str(h))}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{escape(number(v))}</td>" for v in row) + "</tr>" for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def png(image: np.ndarray, alt: str) -> str:
    """An <img> holding IMAGE (BGR) as a base64 PNG data URI."""
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        return f'<p class="note">{escape(alt)}: could not encode the plot</p>'
    data = base64.b64encode(encoded.tobytes()).decode("ascii")
    return f'<img alt="{escape(alt)}" src="data:image/png;base64,{data}">'


def note(text: str) -> str:
    return f'<p class="note">{escape(text)}</p>'


# --- pipeline runs ------------------------------------------------------------------------


def load_report(settings: Settings, job: Job) -> dict[str, Any] | None:
    """The job's report.json, or None when it has none or it cannot be read."""
    where = job.result.get("report") or job.result_path
    if not where:
        return None
    path = job_file(settings, job, str(where))
    if path.is_dir():
        path = path / "report.json"
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return report if isinstance(report, dict) else None


def clutter_section(metrics: Mapping[str, Any]) -> str:
    """Lee et al. Tables 2-3 per scope (camera view / full 360) and reference (dynamic /
    clutter classes), with the DynamicMap SA / DA / AA."""
    rows, plots = [], []
    for scope, by_kind in metrics.items():
        if not isinstance(by_kind, Mapping):
            continue
        for kind, entry in by_kind.items():
            if not isinstance(entry, Mapping):
                continue
            em, sc = entry.get("error_matrix") or {}, entry.get("scores") or {}
            rows.append(
                [
                    scope.replace("_", " "),
                    kind,
                    em.get("overall_accuracy"),
                    em.get("clutter_omission"),
                    em.get("clutter_commission"),
                    em.get("map_omission"),
                    em.get("map_commission"),
                    sc.get("SA"),
                    sc.get("DA"),
                    sc.get("AA"),
                    em.get("points"),
                ]
            )
            if scope == "full" and em:
                matrix = np.array(
                    [
                        [em.get("map_kept", 0), em.get("map_removed", 0)],
                        [em.get("clutter_kept", 0), em.get("clutter_removed", 0)],
                    ]
                )
                image = confusion_image(
                    matrix, ["map", "clutter"], f"clutter error matrix ({kind}, full)"
                )
                plots.append(png(image, f"clutter error matrix {kind}"))
    header = [
        "scope",
        "reference",
        "overall accuracy [%]",
        "clutter omission [%]",
        "clutter commission [%]",
        "map omission [%]",
        "map commission [%]",
        "SA [%]",
        "DA [%]",
        "AA [%]",
        "points",
    ]
    return table(header, rows) + "".join(plots)


def scores_table(scores: Mapping[str, Any]) -> str:
    """Per-class precision / recall / F / support, the overall (macro) row and accuracy."""
    names = scores.get("names", list(scores.get("classes", {})))
    classes = scores.get("classes", {})
    rows = [
        [
            n,
            classes[n].get("precision"),
            classes[n].get("recall"),
            classes[n].get("f1"),
            classes[n].get("support"),
        ]
        for n in names
        if n in classes
    ]
    macro = scores.get("macro")
    if macro:
        over = ", ".join(scores.get("macro_classes", [])) or "classes with support"
        rows.append(
            [
                f"overall (mean of {over})",
                macro.get("precision"),
                macro.get("recall"),
                macro.get("f1"),
                macro.get("support"),
            ]
        )
    if "accuracy" in scores:
        rows.append(["accuracy (all classes)", None, None, scores["accuracy"], None])
    return table(["class", "precision [%]", "recall [%]", "F [%]", "support"], rows)


def phantom_section(metrics: Mapping[str, Any]) -> str:
    """Nagy & Benedek Table I at pillar level (after / before the 5x5 vote) and point level,
    their confusion matrices, and point-level phantom detection per method (Table II)."""
    parts = []
    titles = {
        "pillar": "pillars (after the 5x5 vote)",
        "pillar_raw": "pillars (CNN only)",
        "point": "points",
    }
    for key, title in titles.items():
        scores = metrics.get(key)
        if not isinstance(scores, Mapping):
            continue
        parts.append(f"<h4>{escape(title)}</h4>{scores_table(scores)}")
        if key != "pillar_raw" and scores.get("confusion"):
            names = scores.get("names") or PILLAR_NAMES
            image = confusion_image(np.asarray(scores["confusion"]), names, f"phantom: {title}")
            parts.append(png(image, f"phantom confusion matrix {key}"))
            f_scores = {n: scores["classes"][n].get("f1", float("nan")) for n in names}
            parts.append(png(bar_image(f_scores, f"F per class: {title}", "F [%]"), "F per class"))
    detection = metrics.get("phantom_points")
    if isinstance(detection, Mapping) and detection:
        rows = [
            [m, s.get("precision"), s.get("recall"), s.get("f1"), s.get("support")]
            for m, s in detection.items()
        ]
        parts.append("<h4>phantom points by method</h4>")
        parts.append(table(["method", "precision [%]", "recall [%]", "F [%]", "support"], rows))
    return "".join(parts)


def guardrail_section(metrics: Mapping[str, Any]) -> str:
    """Matsumoto et al. Table 2: slice precision / recall / F before and after the adjacency
    correction, and the point-level scores."""
    titles = {"slice_raw": "slices (CNN)", "slice": "slices (corrected)", "point": "points"}
    rows = [
        [t, s.get("precision"), s.get("recall"), s.get("f1"), s.get("support")]
        for key, t in titles.items()
        if isinstance(s := metrics.get(key), Mapping)
    ]
    parts = []
    if metrics.get("reference"):
        parts.append(note(f"reference: {metrics['reference']}"))
    parts.append(table(["level", "precision [%]", "recall [%]", "F [%]", "support"], rows))
    if rows:
        values = {row[0]: row[3] if row[3] is not None else float("nan") for row in rows}
        parts.append(png(bar_image(values, "guardrail F", "F [%]"), "guardrail F"))
    return "".join(parts)


SECTIONS = {"clutter": clutter_section, "phantom": phantom_section, "guardrail": guardrail_section}


def count_rows(counts: Mapping[str, Any], prefix: str = "") -> list[list[Any]]:
    """One row per count; a nested group ("pillars per class") as one row per member, never a
    Python dict in a cell."""
    rows: list[list[Any]] = []
    for key, value in counts.items():
        name = prefix + key.replace("_", " ")
        if isinstance(value, Mapping):
            rows.extend(count_rows(value, f"{name}: "))
        else:
            rows.append([name, value])
    return rows


def run_section(session: Session, settings: Settings, survey: Survey, pipeline: str) -> str:
    job = latest_succeeded_job(session, survey.id, PIPELINE_JOBS[pipeline])
    head = f"<h2>{escape(pipeline)}</h2>"
    if job is None:
        return head + note("No finished run of this pipeline on this survey.")
    finished = job.finished_at.isoformat(timespec="seconds") if job.finished_at else "n/a"
    head += note(f"job {job.id} ({job.kind}), finished {finished}")
    report = load_report(settings, job)
    if report is None:
        return head + note("The run's report.json is missing or unreadable.")
    counts = report.get("counts")
    if isinstance(counts, Mapping) and counts:
        head += table(["count", "value"], count_rows(counts))
    metrics = report.get("metrics")
    if not isinstance(metrics, Mapping) or not metrics:
        return head + note("No metrics: the survey has no reference labels for this pipeline.")
    return head + SECTIONS[pipeline](metrics)


# --- review state -------------------------------------------------------------------------


def label_section(session: Session, survey_id: int) -> str:
    """Human labels per class and per user, model pre-labels, clutter decisions, guardrail
    model verdicts."""
    per_user = pillar_label_counts(session, survey_id)
    by_source = {s.value: np.zeros(len(PillarClass), dtype=np.int64) for s in LabelSource}
    by_user: dict[str, np.ndarray] = {}
    for username, source, label, n in per_user:
        by_source[LabelSource(source).value][int(label)] += n
        if LabelSource(source) == LabelSource.human:
            row = by_user.setdefault(username or "(deleted user)", np.zeros(4, np.int64))
            row[int(label)] += n
    parts = ["<h2>labels and review</h2>", "<h3>pillar labels per class</h3>"]
    parts.append(
        table(
            ["source", *PILLAR_NAMES, "total"],
            [[s, *map(int, c), int(c.sum())] for s, c in by_source.items()],
        )
    )
    human = by_source[LabelSource.human.value]
    if human.sum():
        bars = dict(zip(PILLAR_NAMES, human.astype(float), strict=True))
        parts.append(png(bar_image(bars, "human pillar labels", "pillars"), "human labels"))
    parts.append("<h3>human pillar labels per user</h3>")
    parts.append(
        table(
            ["user", *PILLAR_NAMES, "total"],
            [[u, *map(int, c), int(c.sum())] for u, c in sorted(by_user.items())],
        )
        if by_user
        else note("No human pillar labels yet.")
    )

    instances = clutter_instance_count(session, survey_id)
    decided = clutter_decision_counts(session, survey_id)
    approved = int(decided.get(Decision.approved, 0))
    rejected = int(decided.get(Decision.rejected, 0))
    parts.append("<h3>clutter decisions</h3>")
    parts.append(
        table(
            ["instances", "approved", "rejected", "pending"],
            [[int(instances), approved, rejected, int(instances) - approved - rejected]],
        )
    )
    verdicts = guardrail_status_counts(session, survey_id)
    parts.append("<h3>guardrail models</h3>")
    parts.append(
        table(
            ["approved", "rejected", "pending"],
            [
                [
                    int(verdicts.get(s, 0))
                    for s in (ModelStatus.approved, ModelStatus.rejected, ModelStatus.pending)
                ]
            ],
        )
    )
    return "".join(parts)


# --- the page -----------------------------------------------------------------------------


def survey_section(session: Session, survey: Survey) -> str:
    frames = frames_summary(session, survey.id)
    rows = [
        ["id", survey.id],
        ["name", survey.name],
        ["format", survey.format],
        ["source", survey.source_path],
        ["frames", survey.frame_count],
        ["points", survey.point_count],
        ["reference labels", survey.has_reference_labels],
        ["poses estimated (odometry)", survey.poses_estimated],
        [
            "origin (x, y, z)",
            f"{survey.origin_x:.3f}, {survey.origin_y:.3f}, {survey.origin_z:.3f}",
        ],
        ["duration [s]", frames.get("duration_s")],
        ["trajectory length [m]", frames.get("trajectory_length_m")],
        ["registered", survey.created_at.isoformat(timespec="seconds")],
    ]
    return "<h2>survey</h2>" + table(["", "value"], rows)


def build_qa_report(session: Session, settings: Settings, survey: Survey, generated_by: str) -> str:
    """The whole page as one HTML string."""
    now = datetime.now(UTC).isoformat(timespec="seconds")
    body = [
        f"<h1>QA report: {escape(survey.name)}</h1>",
        note(f"generated {now} by {generated_by}; percentages as the papers define them"),
        survey_section(session, survey),
        *(run_section(session, settings, survey, p) for p in PIPELINE_JOBS),
        label_section(session, survey.id),
    ]
    title = escape(f"mmsclean QA report: {survey.name}")
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{title}</title><style>{_STYLE}</style></head><body>"
        + "".join(body)
        + "</body></html>\n"
    )
