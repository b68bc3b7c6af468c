"""`/surveys/{survey_id}/exports`: what leaves the product (reviewer role, by the file-kind
rule of `app.api.downloads` that job output files follow too), each download audited as
`export.<name>`.

- `cleaned.laz` / `removed.laz`: the maps of the newest finished clutter run.
- `guardrails.zip?format=glb|obj`: the approved guardrail meshes and a manifest.
- `pillars.csv` / `pillars.npz`: the labelled pillar set (human labels; model pre-labels too
  with `include_model=true`) on the store's world grid.
- `qa-report.html`: survey summary, paper metrics of the newest runs, review state.
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
import tempfile
import zipfile
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Query
from fastapi.responses import FileResponse, Response, StreamingResponse
from sqlmodel import Session, col, select
from starlette.background import BackgroundTask

from app.api.deps import SessionDep, SettingsDep
from app.api.downloads import downloader
from app.api.errors import errors
from app.api.qa_report import PIPELINE_JOBS, build_qa_report, job_file
from app.api.types import Id
from app.core.errors import NotFoundError
from app.core.settings import Settings
from app.store.audit import audit
from app.store.db import commit
from app.store.models import (
    GuardrailModel,
    LabelSource,
    ModelStatus,
    PillarClass,
    PillarLabel,
    Survey,
    User,
)
from app.store.pillar_labels import STORE_GRID
from app.store.surveys import get_survey, latest_succeeded_job

router = APIRouter(
    prefix="/surveys/{survey_id}/exports", tags=["exports"], responses=errors(401, 403, 404)
)

LAS_MEDIA = {".laz": "application/vnd.laszip", ".las": "application/vnd.las"}
LABEL_NAMES = np.array([c.name for c in PillarClass])
SOURCES = [s.value for s in LabelSource]
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


def temp_file(settings: Settings, suffix: str) -> Path:
    """A fresh file under the cache folder, deleted after the response is sent."""
    folder = settings.cache_dir / "exports"
    folder.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(suffix=suffix, dir=folder)
    os.close(fd)
    return Path(name)


def _unlink(path: Path) -> None:
    path.unlink(missing_ok=True)


# --- clutter maps -------------------------------------------------------------------------


def clutter_map(
    session: Session, settings: Settings, survey: Survey, which: str
) -> tuple[Path, int]:
    """The `which` ("cleaned" / "removed") map file of the newest finished clutter run."""
    job = latest_succeeded_job(session, survey.id, PIPELINE_JOBS["clutter"])
    if job is None:
        raise NotFoundError(
            f"survey {survey.id} has no finished clutter run; run the clutter pipeline first"
        )
    where = (job.result.get("files") or {}).get(which)
    if not where:
        raise NotFoundError(f"clutter job {job.id} wrote no {which} map")
    path = job_file(settings, job, str(where))
    if not path.is_file():
        raise NotFoundError(f"{path}: the {which} map of clutter job {job.id} is gone from disk")
    return path, job.id


def _clutter_download(
    which: str, survey_id: int, user: User, session: SessionDep, settings: SettingsDep
) -> FileResponse:
    survey = get_survey(session, survey_id)
    path, job_id = clutter_map(session, settings, survey, which)
    exported(session, user.id, survey, f"{which}_laz", job_id=job_id, file=str(path))
    return FileResponse(
        path,
        media_type=LAS_MEDIA.get(path.suffix.lower(), "application/octet-stream"),
        filename=f"{slug(survey.name)}-{which}{path.suffix.lower()}",
    )


@router.get("/cleaned.laz", response_class=FileResponse)
def cleaned_laz(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("cleaned.laz"))],
    session: SessionDep,
    settings: SettingsDep,
) -> FileResponse:
    """The cleaned map (clutter removed) of the newest finished clutter run."""
    return _clutter_download("cleaned", survey_id, user, session, settings)


@router.get("/removed.laz", response_class=FileResponse)
def removed_laz(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("removed.laz"))],
    session: SessionDep,
    settings: SettingsDep,
) -> FileResponse:
    """The removed points (the clutter itself) of the newest finished clutter run."""
    return _clutter_download("removed", survey_id, user, session, settings)


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
    rows = session.exec(
        select(GuardrailModel, User.username)
        .outerjoin(User, col(User.id) == col(GuardrailModel.decided_by))
        .where(
            GuardrailModel.survey_id == survey.id,
            GuardrailModel.status == ModelStatus.approved,
        )
        .order_by(col(GuardrailModel.guardrail_index))
    ).all()
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


@router.get("/guardrails.zip", response_class=FileResponse)
def guardrails_zip(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("guardrails.zip"))],
    session: SessionDep,
    settings: SettingsDep,
    format: Literal["glb", "obj"] = Query("glb", description="mesh file format"),
) -> FileResponse:
    """The approved guardrail models as meshes, with a manifest.json of their parameters."""
    survey = get_survey(session, survey_id)
    archive = temp_file(settings, ".zip")
    count = write_guardrails_zip(session, survey, format, archive)
    exported(session, user.id, survey, "guardrails_zip", format=format, models=count)
    return FileResponse(
        archive,
        media_type="application/zip",
        filename=f"{slug(survey.name)}-guardrails-{format}.zip",
        background=BackgroundTask(_unlink, archive),
    )


# --- pillar labels ------------------------------------------------------------------------


def pillar_table(session: Session, survey_id: int, include_model: bool) -> dict[str, np.ndarray]:
    """The labelled pillars as columns, ordered by cell id then source; cells decoded on
    `STORE_GRID`."""
    query = (
        select(
            PillarLabel.cell_id,
            PillarLabel.label,
            PillarLabel.source,
            PillarLabel.confidence,
            User.username,
            PillarLabel.updated_at,
        )
        .outerjoin(User, col(User.id) == col(PillarLabel.user_id))
        .where(PillarLabel.survey_id == survey_id)
        .order_by(col(PillarLabel.cell_id), col(PillarLabel.source))
    )
    if not include_model:
        query = query.where(PillarLabel.source == LabelSource.human)
    rows = session.exec(query).all()
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


@router.get("/pillars.csv", response_class=StreamingResponse)
def pillars_csv(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("pillars.csv"))],
    session: SessionDep,
    include_model: bool = Query(False, description="add the model's pre-labels"),
) -> StreamingResponse:
    """One row per labelled pillar: id, grid indices, centre, label, source, confidence, user,
    last change (UTC)."""
    survey = get_survey(session, survey_id)
    t = pillar_table(session, survey_id, include_model)
    exported(
        session, user.id, survey, "pillars_csv", rows=len(t["cell_id"]), include_model=include_model
    )
    name = f"{slug(survey.name)}-pillars.csv"
    return StreamingResponse(
        csv_pieces(t),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )


@router.get("/pillars.npz", response_class=FileResponse)
def pillars_npz(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("pillars.npz"))],
    session: SessionDep,
    settings: SettingsDep,
    include_model: bool = Query(False, description="add the model's pre-labels"),
) -> FileResponse:
    """The CSV's columns as numpy arrays, plus the grid (origin, cell size) and class names."""
    survey = get_survey(session, survey_id)
    t = pillar_table(session, survey_id, include_model)
    path = temp_file(settings, ".npz")
    write_pillars_npz(t, path)
    exported(
        session, user.id, survey, "pillars_npz", rows=len(t["cell_id"]), include_model=include_model
    )
    return FileResponse(
        path,
        media_type="application/octet-stream",
        filename=f"{slug(survey.name)}-pillars.npz",
        background=BackgroundTask(_unlink, path),
    )


# --- QA report ----------------------------------------------------------------------------


@router.get("/qa-report.html", response_class=Response)
def qa_report(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("qa-report.html"))],
    session: SessionDep,
    settings: SettingsDep,
) -> Response:
    """A self-contained HTML page: survey, paper metrics of the newest runs, review state."""
    survey = get_survey(session, survey_id)
    page = build_qa_report(session, settings, survey, user.username)
    exported(session, user.id, survey, "qa_report", bytes=len(page))
    name = f"{slug(survey.name)}-qa-report.html"
    return Response(
        page,
        media_type="text/html; charset=utf-8",
        headers={"Content-Disposition": f'inline; filename="{name}"'},
    )
