"""The export writers: what `/surveys/{id}/exports` sends and `mmsclean export` writes (the
maps of the newest clutter run, approved guardrail meshes zipped with a manifest, the labelled
pillar set as CSV / npz), each whole or not at all, and the audit record of a download."""

from __future__ import annotations

import csv
import io
import json
import re
import zipfile
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from sqlmodel import Session

from app.core.errors import NotFoundError
from app.core.labels import PillarClass
from app.core.settings import Settings
from app.pipelines.tiling import MAPS
from app.reports.qa_report import PIPELINE_JOBS, job_file
from app.store.audit import audit
from app.store.db import commit
from app.store.exports import approved_guardrail_models, pillar_label_rows
from app.store.models import GuardrailModel, Job, Survey
from app.store.pillar_labels import STORE_GRID
from app.store.surveys import latest_succeeded_job

LABEL_NAMES = np.array([c.name for c in PillarClass])
CSV_HEADER = [
    "cell_id", "ix", "iy", "x", "y", "label", "label_name", "source", "confidence", "user",
    "updated_at",
]  # fmt: skip
CSV_CHUNK = 50_000  # rows per streamed piece


def slug(name: str) -> str:
    """A survey name made safe for a download file name."""
    return re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-.") or "survey"


def exported(
    session: Session, user_id: int | None, survey: Survey, name: str, **payload: Any
) -> None:
    """Record the download in the audit trail (committed before any byte goes out)."""
    audit(session, user_id, f"export.{name}", "survey", survey.id, **payload)
    commit(session)


# --- maps of the pipelines that remove points ----------------------------------------------

REMOVERS = ("clutter", "phantom")  # the pipelines whose runs write cleaned / removed maps


def removal_run(session: Session, survey: Survey, source: str = "newest") -> Job:
    """The newest finished run of `source` ("clutter", "phantom", or "newest": whichever of
    them finished last)."""
    pipelines = REMOVERS if source == "newest" else (source,)
    kinds = [kind for p in pipelines for kind in PIPELINE_JOBS[p]]
    job = latest_succeeded_job(session, survey.id, kinds)
    if job is None:
        named = " or ".join(pipelines)
        raise NotFoundError(
            f"survey {survey.id} has no finished {named} run; run the {named} pipeline first"
        )
    return job


def map_file(settings: Settings, job: Job, which: str) -> Path:
    """The `which` ("cleaned" / "removed") map file `job` wrote."""
    where = (job.result.get("files") or {}).get(which)
    if not where:
        raise NotFoundError(f"{job.kind} job {job.id} wrote no {which} map (nothing {which})")
    path = job_file(settings, job, str(where))
    if not path.is_file():
        raise NotFoundError(f"{path}: the {which} map of {job.kind} job {job.id} is gone from disk")
    return path


def removal_map(
    session: Session, settings: Settings, survey: Survey, which: str, source: str = "newest"
) -> tuple[Path, Job]:
    """The `which` ("cleaned" / "removed") map file of the newest finished run of `source`
    (`removal_run`)."""
    job = removal_run(session, survey, source)
    return map_file(settings, job, which), job


def removal_maps(
    session: Session, settings: Settings, survey: Survey, source: str = "newest"
) -> tuple[dict[str, Path], Job]:
    """Every map ({"cleaned": path, "removed": path}, those written) of the newest finished
    run of `source`; a map the run wrote but that is gone from disk is an error."""
    job = removal_run(session, survey, source)
    written = job.result.get("files") or {}
    maps = {which: map_file(settings, job, which) for which in MAPS if written.get(which)}
    if not maps:
        raise NotFoundError(f"{job.kind} job {job.id} wrote no map (nothing cleaned or removed)")
    return maps, job


def remover_of(job: Job) -> str:
    """The pipeline (one of `REMOVERS`) whose run `job` is."""
    return next(p for p in REMOVERS if job.kind in PIPELINE_JOBS[p])


# --- guardrail meshes ---------------------------------------------------------------------


def mesh_file(model: GuardrailModel, fmt: str) -> Path:
    """The model's mesh in FMT: `mesh_path` is the glb, `params["files"]` the others (absolute,
    or relative to the job folder, as in the run report)."""
    mesh = Path(model.mesh_path)
    if fmt == "glb" and mesh.suffix.lower() == ".glb":
        return mesh
    where = (model.params.get("files") or {}).get(fmt)
    if not where:
        return mesh.with_suffix(f".{fmt}")
    path = Path(where)
    return path if path.is_absolute() else mesh.parent / path.name


def write_guardrails_zip(session: Session, survey: Survey, fmt: str, archive: Path) -> int:
    """The approved guardrail models' meshes in FMT and a manifest.json of their parameters,
    zipped to ARCHIVE (whole or not at all: on any failure ARCHIVE is removed); the number of
    models."""
    try:
        return _write_guardrails_zip(session, survey, fmt, archive)
    except BaseException:
        archive.unlink(missing_ok=True)
        raise


def _write_guardrails_zip(session: Session, survey: Survey, fmt: str, archive: Path) -> int:
    rows = approved_guardrail_models(session, survey.id)
    if not rows:
        raise NotFoundError(
            f"survey {survey.id} has no approved guardrail model; approve one in the review first"
        )
    stem = slug(survey.name)
    members, manifest = [], []
    for model, decided_by in rows:
        path = mesh_file(model, fmt)
        if not path.is_file():
            raise NotFoundError(f"{path}: mesh of approved guardrail model {model.id} is missing")
        arcname = f"{stem}-guardrail-{model.guardrail_index:03d}-{model.kind.value}.{fmt}"
        members.append((path, arcname))
        manifest.append(
            {
                "id": model.id,
                "guardrail_index": model.guardrail_index,
                "kind": model.kind.value,
                "file": arcname,
                "unit_count": model.unit_count,
                "icp_residual": model.icp_residual,
                "approved_by": decided_by,
                "approved_at": model.decided_at.isoformat() if model.decided_at else None,
                "params": {k: v for k, v in model.params.items() if k != "files"},
            }
        )
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for path, arcname in members:
            zf.write(path, arcname)
        info = {"survey": survey.name, "survey_id": survey.id, "format": fmt}
        zf.writestr("manifest.json", json.dumps({**info, "models": manifest}, indent=1))
    return len(members)


# --- pillar labels ------------------------------------------------------------------------


def pillar_table(session: Session, survey_id: int, include_model: bool) -> dict[str, np.ndarray]:
    """The labelled pillars as columns, ordered by cell id then source; cells decoded on
    `STORE_GRID`."""
    rows = pillar_label_rows(session, survey_id, include_model)
    what = "pillar labels" if include_model else "human pillar labels"
    if not rows:
        raise NotFoundError(f"survey {survey_id} has no {what} to export")
    cells, labels, sources, confidence, users, updated = zip(*rows, strict=True)
    cell_ids = np.asarray(cells, dtype=np.int64)
    ix, iy = STORE_GRID.decode(cell_ids)
    centres = STORE_GRID.cell_center(ix, iy)
    return {
        "cell_id": cell_ids,
        "ix": ix,
        "iy": iy,
        "x": centres[:, 0],
        "y": centres[:, 1],
        "label": np.asarray(labels, dtype=np.uint8),
        "source": np.asarray(sources, dtype=str),
        "confidence": np.asarray(confidence, dtype=np.float64),  # None -> NaN
        "user": np.asarray(["" if u is None else u for u in users], dtype=str),
        "updated_at": np.asarray(list(map(datetime.isoformat, updated)), dtype=str),
    }


def csv_pieces(t: dict[str, np.ndarray]) -> Iterator[str]:
    """The CSV text in pieces of CSV_CHUNK rows (rows formatted by the csv module in C)."""
    conf = np.round(t["confidence"], 4).astype(object)
    conf[np.isnan(t["confidence"])] = ""
    columns = [
        t["cell_id"].tolist(),
        t["ix"].tolist(),
        t["iy"].tolist(),
        np.round(t["x"], 3).tolist(),
        np.round(t["y"], 3).tolist(),
        t["label"].tolist(),
        LABEL_NAMES[t["label"]].tolist(),
        t["source"].tolist(),
        conf.tolist(),
        t["user"].tolist(),
        t["updated_at"].tolist(),
    ]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    for start in range(0, len(t["cell_id"]), CSV_CHUNK):
        writer.writerows(zip(*(c[start : start + CSV_CHUNK] for c in columns), strict=True))
        yield buffer.getvalue()
        buffer.seek(0)
        buffer.truncate()


def write_pillars_npz(t: dict[str, np.ndarray], path: Path) -> None:
    """The pillar table's columns, the grid (origin, cell size) and class names (whole or not at
    all: a failed write leaves no file)."""
    try:
        with open(path, "wb") as f:  # an open file: numpy adds no ".npz" to the name
            np.savez_compressed(
                f,
                **t,
                label_names=LABEL_NAMES,
                grid_origin=np.array([STORE_GRID.origin_x, STORE_GRID.origin_y]),
                cell_size=np.float64(STORE_GRID.cell_size),
            )
    except BaseException:
        Path(path).unlink(missing_ok=True)
        raise
