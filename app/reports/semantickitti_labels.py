"""SemanticKITTI `.label` files of the newest clutter run, as point_labeler and the SemanticKITTI
tooling read them: one file per frame, a uint32 per point of the frame in its point order.

The run's review units say which instance owns each point (`<run>/instances/<frame>.npz`), the
store what the run called each instance (class, moving, track) and the reviewers' verdicts, which
are applied as `clutter:recompute` applies them (after the reviewers' corrections of the
membership) (approved: removed, rejected: kept, pending: the
pipeline's flag), so the labels are the review as it stands at the export. Ids:

- a removed point: its instance's class (`CLUTTER_CLASS_SEMANTIC`), as SemanticKITTI's moving id
  (`MOVING_OFFSET`) when the run found the instance moving, else as the static id (parked
  clutter); a removed point of no known class is moving-other-vehicle (259) when moving, else
  other-object (99): SemanticKITTI has no moving id of unknown class;
- a kept point of a classified, not moving instance that no reviewer rejected (a parked object
  the run left in the map): that static id; every other kept point 0 (unlabeled);
- instance (upper 16 bits): the track + 1 for tracked instances (one id along the drive, as
  SemanticKITTI's), the next free ids for the others, 0 for unlabeled points and for ids past
  65535.

Written a frame at a time into the zip: one frame's arrays are held, never the survey's.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sqlmodel import Session

from app.core.errors import ConflictError, NotFoundError
from app.core.labels import (
    CLUTTER_CLASS_SEMANTIC,
    MOVING_OFFSET,
    Semantic,
    semantic_name,
)
from app.core.settings import Settings
from app.io.semantickitti import label_bytes
from app.pipelines.clutter.review_units import reviewed_frame
from app.reports.exports import slug
from app.reports.qa_report import job_file
from app.store import clutter_corrections, clutter_review
from app.store.clutter_review import InstanceClass
from app.store.models import Decision, Job, Survey
from app.store.surveys import frame_point_counts

UNKNOWN_MOVING = int(Semantic.OTHER_VEHICLE)  # moving, class unknown: moving-other-vehicle
UNKNOWN_STATIC = int(Semantic.OTHER_OBJECT)
MAX_INSTANCE = 0xFFFF
# static id -> moving id, the identity elsewhere
MOVING = np.arange(256, dtype=np.uint16)
for _static, _moving in MOVING_OFFSET.items():
    MOVING[_static] = _moving
VERDICT = {Decision.approved: 1, Decision.rejected: 0, Decision.pending: -1}


@dataclass
class FrameTable:
    """Per instance index of one frame: static SemanticKITTI id (0 unknown), moving, rejected,
    instance id."""

    static: np.ndarray
    moving: np.ndarray
    rejected: np.ndarray
    ident: np.ndarray

    @classmethod
    def of(cls, rows: list[tuple[InstanceClass, int]], size: int) -> FrameTable:
        size = max([size, 1, *(r.instance_index + 1 for r, _ in rows)])  # 1: nothing owned
        table = cls(
            np.zeros(size, np.uint16), np.zeros(size, bool), np.zeros(size, bool),
            np.zeros(size, np.uint16),
        )  # fmt: skip
        for row, ident in rows:  # a loop over instances, not points
            k = row.instance_index
            table.static[k] = CLUTTER_CLASS_SEMANTIC.get(row.class_name, 0)
            table.moving[k] = bool(row.moving)
            table.rejected[k] = row.decision == Decision.rejected
            table.ident[k] = ident
        return table


def frame_labels(
    owner: np.ndarray, removed: np.ndarray, table: FrameTable
) -> tuple[np.ndarray, np.ndarray]:
    """(semantic, instance) uint16 per point of a frame (the ids of the module docstring)."""
    owned = owner >= 0
    k = np.where(owned, owner, 0)
    static = np.where(owned, table.static[k], 0)
    moving = table.moving[k] & owned
    known = static > 0
    gone_id = np.where(
        moving,
        MOVING[np.where(known, static, UNKNOWN_MOVING)],
        np.where(known, static, UNKNOWN_STATIC),
    )
    parked = ~removed & owned & known & ~moving & ~table.rejected[k]
    semantic = np.where(removed, gone_id, np.where(parked, static, 0)).astype(np.uint16)
    instance = np.where((removed & owned) | parked, table.ident[k], 0).astype(np.uint16)
    return semantic, instance


def instance_ids(rows: list[InstanceClass]) -> tuple[list[int], int]:
    """An instance id per row (track + 1, else the next free id, in the rows' order; 0 past
    65535) and how many got 0."""
    tracks = [r.track_id for r in rows if r.track_id is not None]
    following = (max(tracks) + 2) if tracks else 1
    ids = []
    for row in rows:
        if row.track_id is not None:
            ids.append(row.track_id + 1)
        else:
            ids.append(following)
            following += 1
    lost = sum(i > MAX_INSTANCE for i in ids)
    return [0 if i > MAX_INSTANCE else i for i in ids], lost


def labelled_run(session: Session, settings: Settings, survey: Survey) -> tuple[Job, Path]:
    """The newest finished clutter run and its review units' folder, which the store's
    instances must come from."""
    job = clutter_review.latest_run(session, survey.id)
    if job is None:
        raise NotFoundError(
            f"survey {survey.id} has no finished clutter run; run the clutter pipeline first"
        )
    where = (job.result.get("files") or {}).get("instances")
    if not where:
        raise NotFoundError(f"{job.kind} job {job.id} wrote no review units (instances)")
    folder = job_file(settings, job, str(where))
    if not folder.is_dir():
        raise NotFoundError(f"{folder}: the review units of {job.kind} job {job.id} are gone")
    return job, folder


def write_semantickitti_zip(
    session: Session, settings: Settings, survey: Survey, archive: Path
) -> dict[str, Any]:
    """The labels zip (module docstring) with a README.txt and manifest.json, whole or not at
    all (on any failure ARCHIVE is removed); returns the manifest."""
    try:
        return _write_zip(session, settings, survey, archive)
    except BaseException:
        archive.unlink(missing_ok=True)
        raise


def sequence_name(survey: Survey) -> str:
    """A SemanticKITTI sequence keeps its folder's name ("04"), so the labels drop in beside its
    velodyne/; other surveys go by their name."""
    if survey.format == "semantickitti":
        return slug(Path(survey.source_path).name)
    return slug(survey.name)


def _write_zip(
    session: Session, settings: Settings, survey: Survey, archive: Path
) -> dict[str, Any]:
    job, folder = labelled_run(session, settings, survey)
    rows = clutter_review.instance_classes(session, survey.id)
    run = clutter_review.run_folder_of([r.mask_path for r in rows])
    if run is not None and run.resolve() != folder.parent.resolve():
        raise ConflictError(
            f"the survey's clutter instances come from {run}, not from {job.kind} job {job.id} "
            f"({folder.parent}); run clutter again"
        )
    frames = frame_point_counts(session, survey.id)
    if not frames:
        raise NotFoundError(f"survey {survey.id} has no frames")
    ids, lost = instance_ids(rows)
    by_frame: dict[str, list[tuple[InstanceClass, int]]] = {}
    for row, ident in zip(rows, ids, strict=True):
        by_frame.setdefault(row.frame_id, []).append((row, ident))
    unknown = set(by_frame) - {f for f, _ in frames}
    if unknown:
        raise ConflictError(f"clutter instances name frame {sorted(unknown)[0]!r}, not in survey")
    corrections = clutter_corrections.survey_corrections(session, survey.id)
    sequence = sequence_name(survey)
    totals = np.zeros(1 << 16, dtype=np.int64)
    written = []
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for frame_id, count in frames:  # a frame at a time
            mine = by_frame.get(frame_id, [])
            verdicts = [(r.instance_index, VERDICT[r.decision]) for r, _ in mine]
            reviewed = reviewed_frame(
                folder, frame_id, count or None, verdicts, corrections.get(frame_id, ())
            )
            table = FrameTable.of(mine, int(reviewed.owner.max(initial=-1)) + 1)
            semantic, instance = frame_labels(reviewed.owner, reviewed.removed, table)
            name = f"sequences/{sequence}/labels/{slug(frame_id)}.label"
            zf.writestr(name, label_bytes(semantic, instance))
            totals += np.bincount(semantic, minlength=len(totals))
            written.append({"frame_id": frame_id, "file": name, "points": len(semantic)})
        tally = {d.value: 0 for d in Decision}
        for row in rows:
            tally[row.decision.value] += 1
        used = {int(i): semantic_name(int(i)) for i in np.flatnonzero(totals)}
        manifest = {
            "survey": survey.name,
            "survey_id": survey.id,
            "format": "SemanticKITTI .label: uint32 little-endian per point, semantic id in the "
            "lower 16 bits, instance id in the upper 16",
            "job_id": job.id,
            "job_kind": job.kind,
            "job_finished_at": job.finished_at.isoformat() if job.finished_at else None,
            "run_folder": str(folder.parent),
            "decisions": tally,
            "instances_without_id": lost,
            "ids": id_table(),
            "points_per_id": {f"{i} {n}": int(totals[i]) for i, n in used.items()},
            "frames": written,
        }
        zf.writestr("manifest.json", json.dumps(manifest, indent=1))
        zf.writestr("README.txt", readme(survey, job, sequence, len(written)))
    return manifest


def id_table() -> dict[str, str]:
    """The ids this export writes, with SemanticKITTI's names."""
    ids = [0, *sorted({int(s) for s in CLUTTER_CLASS_SEMANTIC.values()}), UNKNOWN_STATIC]
    ids += sorted(set(MOVING_OFFSET.values()))
    return {str(i): semantic_name(i) for i in ids}


def readme(survey: Survey, job: Job, sequence: str, frames: int) -> str:
    table = "\n".join(f"  {i:>3}  {name}" for i, name in id_table().items())
    return f"""SemanticKITTI labels of survey {survey.name!r} (id {survey.id}), written by mmsclean
from clutter run job {job.id} ({job.kind}) and the review decisions as they stood at the export.

sequences/{sequence}/labels/<frame-id>.label, {frames} frames: one uint32 (little-endian) per
point of the frame, in the frame's point order; semantic id = value & 0xFFFF, instance id =
value >> 16 (the SemanticKITTI format; point_labeler reads it beside velodyne/).

Removed points carry their object's class: the moving id when the run found the object moving,
the static id when it removed it as parked clutter. A removed point of no known class is
moving-other-vehicle (259) when moving, else other-object (99). Kept points are 0 (unlabeled),
except those of a classified, not moving object the run kept and no reviewer rejected (its
static id). Instance ids: track + 1 for tracked objects (one id along the drive), the next free
ids for the others; manifest.json lists the run, the decisions and the points per id.

Ids written:
{table}
"""
