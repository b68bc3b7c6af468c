"""`/surveys/{survey_id}/exports`: what leaves the product (reviewer role, by the file-kind
rule of `app.api.downloads` that job output files follow too), each download audited as
`export.<name>`; the files themselves come from the writers in `app.reports`.

- `cleaned.laz` / `removed.laz`: the maps of the newest finished run that removes points
  (`?source=clutter|phantom` picks the pipeline; default whichever finished last), with the
  survey's CRS as a WKT VLR when its LAS header records one (`X-Mmsclean-CRS` says which).
- `classified.laz`: both maps joined, ASPRS classes and mmsclean labels per point.
- `cleaned.pcd` / `map.pcd`: the cleaned map, or both maps, as binary PCD with x y z intensity
  label (label = mmsclean's per-point label).
- `semantickitti-labels.zip`: SemanticKITTI `.label` files per frame of the newest clutter run
  as reviewed, with a README and manifest.
- `guardrails.zip?format=glb|obj`: the approved guardrail meshes and a manifest.
- `pillars.csv` / `pillars.npz`: the labelled pillar set (human labels; model pre-labels too
  with `include_model=true`) on the store's world grid.
- `qa-report.html`: survey summary, paper metrics of the newest runs, review state.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query
from fastapi.responses import FileResponse, Response, StreamingResponse
from starlette.background import BackgroundTask

from app.api.deps import SessionDep, SettingsDep
from app.api.downloads import downloader
from app.api.errors import errors
from app.api.types import Id
from app.core.settings import Settings
from app.reports.combined_maps import write_combined_map
from app.reports.exports import (
    csv_pieces,
    exported,
    pillar_table,
    remover_of,
    slug,
    write_guardrails_zip,
    write_pillars_npz,
)
from app.reports.map_exports import map_with_crs, write_classified_laz, write_map_pcd
from app.reports.qa_report import build_qa_report
from app.reports.semantickitti_labels import write_semantickitti_zip
from app.store.models import Survey, User
from app.store.surveys import get_survey

router = APIRouter(
    prefix="/surveys/{survey_id}/exports", tags=["exports"], responses=errors(401, 403, 404)
)

LAS_MEDIA = {".laz": "application/vnd.laszip", ".las": "application/vnd.las"}


def temp_file(settings: Settings, suffix: str) -> Path:
    """A fresh file under the cache folder, deleted after the response is sent."""
    folder = settings.cache_dir / "exports"
    folder.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(suffix=suffix, dir=folder)
    os.close(fd)
    return Path(name)


def _unlink(path: Path) -> None:
    path.unlink(missing_ok=True)


def _sent_once(path: Path, media_type: str, filename: str) -> FileResponse:
    """A `temp_file` sent as the attachment `filename`, deleted once it is sent."""
    return FileResponse(
        path, media_type=media_type, filename=filename, background=BackgroundTask(_unlink, path)
    )


# --- clutter maps -------------------------------------------------------------------------


MapSource = Literal["newest", "clutter", "phantom"]
SOURCE = Query(
    "newest", description="the pipeline whose run: clutter, phantom, or the newest of both"
)
# the cleaned and removed LAZ maps can also be both runs combined (`combined_maps`)
CombinableSource = Literal["newest", "clutter", "phantom", "combined"]
COMBINABLE_SOURCE = Query(
    "newest",
    description="the pipeline whose run: clutter, phantom, the newest of both, or combined "
    "(what either removed left out of one map)",
)


def header_text(text: str) -> str:
    """`text` as an HTTP header value (latin-1, one line)."""
    return " ".join(text.split()).encode("latin-1", "replace").decode("latin-1")


def _map_download(
    which: str, survey_id: int, user: User, session: SessionDep, settings: SettingsDep, source: str
) -> FileResponse:
    survey = get_survey(session, survey_id)
    if source == "combined":
        return _combined_download(which, survey, user, session, settings)
    dest = temp_file(settings, ".laz")
    try:
        path, job, crs = map_with_crs(session, settings, survey, which, source, dest)
        exported(session, user.id, survey, f"{which}_laz", job_id=job.id, file=str(path), crs=crs)
    except BaseException:
        dest.unlink(missing_ok=True)
        raise
    name = f"{slug(survey.name)}-{remover_of(job)}-{which}{path.suffix.lower()}"
    media = LAS_MEDIA.get(path.suffix.lower(), "application/octet-stream")
    headers = {"X-Mmsclean-CRS": header_text(crs)}
    if path == dest:  # a copy with the CRS
        response = _sent_once(dest, media, name)
        response.headers.update(headers)
        return response
    dest.unlink(missing_ok=True)
    return FileResponse(path, media_type=media, filename=name, headers=headers)


def _combined_download(
    which: str, survey: Survey, user: User, session: SessionDep, settings: SettingsDep
) -> FileResponse:
    """The `which` map of the newest clutter and phantom runs combined (`combined_maps`)."""
    dest = temp_file(settings, ".laz")
    try:
        jobs, count, crs = write_combined_map(session, settings, survey, which, dest)
        exported(session, user.id, survey, f"{which}_laz", source="combined",
                 job_ids=[j.id for j in jobs], points=count, crs=crs)  # fmt: skip
    except BaseException:
        dest.unlink(missing_ok=True)
        raise
    response = _sent_once(dest, LAS_MEDIA[".laz"], f"{slug(survey.name)}-combined-{which}.laz")
    response.headers["X-Mmsclean-CRS"] = header_text(crs)
    return response


@router.get("/cleaned.laz", response_class=FileResponse)
def cleaned_laz(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("cleaned.laz"))],
    session: SessionDep,
    settings: SettingsDep,
    source: CombinableSource = COMBINABLE_SOURCE,
) -> FileResponse:
    """The cleaned map (what was removed left out) of the newest finished clutter or phantom
    run."""
    return _map_download("cleaned", survey_id, user, session, settings, source)


@router.get("/removed.laz", response_class=FileResponse)
def removed_laz(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("removed.laz"))],
    session: SessionDep,
    settings: SettingsDep,
    source: CombinableSource = COMBINABLE_SOURCE,
) -> FileResponse:
    """The removed points (clutter or phantoms) of the newest finished clutter or phantom
    run."""
    return _map_download("removed", survey_id, user, session, settings, source)


@router.get("/classified.laz", response_class=FileResponse)
def classified_laz(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("classified.laz"))],
    session: SessionDep,
    settings: SettingsDep,
    source: MapSource = SOURCE,
) -> FileResponse:
    """The cleaned and removed maps of the newest clutter or phantom run as one LAZ: ASPRS
    classes (`app.io.asprs`), mmsclean labels, the survey's CRS when it has one."""
    survey = get_survey(session, survey_id)
    dest = temp_file(settings, ".laz")
    try:
        job, points, crs = write_classified_laz(session, settings, survey, source, dest)
        exported(session, user.id, survey, "classified_laz", job_id=job.id, points=points, crs=crs)
    except BaseException:
        dest.unlink(missing_ok=True)
        raise
    response = _sent_once(
        dest, LAS_MEDIA[".laz"], f"{slug(survey.name)}-{remover_of(job)}-classified.laz"
    )
    response.headers["X-Mmsclean-CRS"] = header_text(crs)
    return response


PCD_MAPS = {"cleaned": ("cleaned",), "map": ("cleaned", "removed")}


def _pcd_download(
    name: str, survey_id: int, user: User, session: SessionDep, settings: SettingsDep, source: str
) -> FileResponse:
    survey = get_survey(session, survey_id)
    dest = temp_file(settings, ".pcd")
    try:
        job, points = write_map_pcd(session, settings, survey, source, PCD_MAPS[name], dest)
        exported(session, user.id, survey, f"{name}_pcd", job_id=job.id, points=points)
    except BaseException:
        dest.unlink(missing_ok=True)
        raise
    filename = f"{slug(survey.name)}-{remover_of(job)}-{name}.pcd"
    return _sent_once(dest, "application/octet-stream", filename)


@router.get("/cleaned.pcd", response_class=FileResponse)
def cleaned_pcd(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("cleaned.pcd"))],
    session: SessionDep,
    settings: SettingsDep,
    source: MapSource = SOURCE,
) -> FileResponse:
    """The cleaned map as binary PCD (x y z from the survey's origin, intensity, label)."""
    return _pcd_download("cleaned", survey_id, user, session, settings, source)


@router.get("/map.pcd", response_class=FileResponse)
def map_pcd(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("map.pcd"))],
    session: SessionDep,
    settings: SettingsDep,
    source: MapSource = SOURCE,
) -> FileResponse:
    """The cleaned and removed maps as one binary PCD whose label field tells them apart."""
    return _pcd_download("map", survey_id, user, session, settings, source)


# --- SemanticKITTI labels -----------------------------------------------------------------


@router.get("/semantickitti-labels.zip", response_class=FileResponse)
def semantickitti_labels(
    survey_id: Id,
    user: Annotated[User, Depends(downloader("semantickitti-labels.zip"))],
    session: SessionDep,
    settings: SettingsDep,
) -> FileResponse:
    """SemanticKITTI `.label` files per frame of the newest clutter run, as reviewed."""
    survey = get_survey(session, survey_id)
    archive = temp_file(settings, ".zip")
    try:
        manifest = write_semantickitti_zip(session, settings, survey, archive)
        exported(
            session, user.id, survey, "semantickitti_labels", job_id=manifest["job_id"],
            frames=len(manifest["frames"]),
        )  # fmt: skip
    except BaseException:
        archive.unlink(missing_ok=True)
        raise
    name = f"{slug(survey.name)}-semantickitti-labels.zip"
    return _sent_once(archive, "application/zip", name)


# --- guardrail meshes ---------------------------------------------------------------------


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
    return _sent_once(archive, "application/zip", f"{slug(survey.name)}-guardrails-{format}.zip")


# --- pillar labels ------------------------------------------------------------------------


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
    return _sent_once(path, "application/octet-stream", f"{slug(survey.name)}-pillars.npz")


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
