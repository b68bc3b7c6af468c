"""`/surveys`: list and inspect surveys, import one from a server path, upload one, declare its
sensor kind, delete one.

Imports read only inside `allowed_import_root` (symlinks resolved); uploads are streamed under
`surveys_dir/<uuid>/` and registered like imports. A survey is opened with its reader before it
is registered, so bad data answers 422 with the reader's one-line message and leaves nothing
behind. A drive that takes long to open (LiDAR odometry for a KITTI raw drive without OXTS) can
be imported by a worker instead: `POST /jobs` with kind `import:survey` (app.jobs.survey_tasks).
The sensor kind (rotating / profile, app.core.sensors) is declared at import or told by the
reader or the point times; `PATCH /surveys/{id}` declares it later (every run uses the model
for that kind).
"""

from __future__ import annotations

import re
import uuid
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request, Response
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from app.api.deps import Annotator, CurrentUser, Reviewer, SessionDep, SettingsDep
from app.api.errors import errors
from app.api.schemas import JobBrief
from app.api.types import FileName, Id, ImportPath
from app.api.uploads import check_upload_name, extract_zip, receive_upload, remove_tree
from app.core.errors import InputError
from app.core.sensors import SensorKind
from app.io.import_root import resolve_import_path
from app.jobs.survey_tasks import queue_viewer_map
from app.review.surveys import import_source
from app.store.models import SurveyBase
from app.store.pillar_reads import label_counts
from app.store.surveys import (
    delete_survey,
    frames_summary,
    get_survey,
    latest_jobs,
    list_surveys,
    set_sensor_kind,
    surveys_using,
)

router = APIRouter(prefix="/surveys", tags=["surveys"], responses=errors(401))

UPLOAD_FOLDER = re.compile(r"^[0-9a-f]{32}$")  # uuid4().hex: only folders uploads made

# the kinds a person declares (app.core.sensors.KNOWN_KINDS); absent at import: detected
DeclaredSensor = Literal["rotating", "profile"]
SENSOR_HELP = "rotating (spinning multi-beam) or profile (MMS line scanner); detected when absent"


class SurveyPublic(SurveyBase):  # the origin as one (x, y, z): `Survey.origin`
    model_config = ConfigDict(json_schema_serialization_defaults_required=True)  # all answered

    id: int
    origin: tuple[float, float, float]
    created_by: int | None
    sensor_kind: SensorKind
    sensor_note: str = Field(description="how the kind was told; empty: not looked at yet")


class SurveyDetail(SurveyPublic):
    frames: dict[str, Any]
    latest_jobs: dict[str, JobBrief]
    pillar_labels: dict[str, list[int]]  # source -> pillars per class


class SurveyImport(BaseModel):
    path: ImportPath = Field(description="inside the import root")
    format: str | None = Field(None, description="reader name; detected when absent")
    name: str | None = Field(None, min_length=1, max_length=255)
    sensor: DeclaredSensor | None = Field(None, description=SENSOR_HELP)


class SurveyChange(BaseModel):
    model_config = ConfigDict(extra="forbid")

    sensor_kind: DeclaredSensor = Field(description="the scanner kind that recorded the survey")


@router.get("", response_model=list[SurveyPublic])
def surveys(_: CurrentUser, session: SessionDep) -> list[SurveyPublic]:
    """Every survey with its frame and point counts."""
    return [SurveyPublic.model_validate(s) for s in list_surveys(session)]


class ImportRoot(BaseModel):
    path: str = Field(description="the server folder imports read from (MMSCLEAN_IMPORT_ROOT)")


@router.get("/import-root", response_model=ImportRoot, responses=errors(403))
def import_root(_: Annotator, settings: SettingsDep) -> ImportRoot:
    """Where the import form's paths are read from (annotator role: those who may import), so
    the form can name the folder instead of the variable that sets it."""
    return ImportRoot(path=str(settings.allowed_import_root))


@router.get("/{survey_id}", response_model=SurveyDetail, responses=errors(404))
def survey_detail(survey_id: Id, _: CurrentUser, session: SessionDep) -> SurveyDetail:
    """One survey: its frames summarised, the newest job of each kind, pillar label counts."""
    survey = get_survey(session, survey_id)
    jobs = {k: JobBrief.model_validate(j) for k, j in latest_jobs(session, survey_id).items()}
    return SurveyDetail.model_validate(
        survey,
        update={
            "frames": frames_summary(session, survey_id),
            "latest_jobs": jobs,
            "pillar_labels": label_counts(session, survey_id),
        },
    )


@router.post(
    "/import", response_model=SurveyPublic, status_code=201, responses=errors(400, 403, 422)
)
def import_survey(
    body: SurveyImport, user: Annotator, session: SessionDep, settings: SettingsDep
) -> SurveyPublic:
    """Register a survey from a path inside the import root (annotator role)."""
    source = resolve_import_path(body.path, settings.allowed_import_root)
    survey = import_source(
        session,
        source,
        body.format,
        body.name,
        user.id,
        "survey.import",
        sensor=declared(body.sensor),
        requested=body.path,
    )
    queue_viewer_map(session, survey, user.id, settings)  # its first scene ready at once
    return SurveyPublic.model_validate(survey)


@router.patch("/{survey_id}", response_model=SurveyPublic, responses=errors(403, 404, 422))
def change_survey(
    survey_id: Id, body: SurveyChange, user: Annotator, session: SessionDep
) -> SurveyPublic:
    """Declare a survey's sensor kind (annotator role; audited): its runs use the model for
    that kind from then on."""
    kind = SensorKind(body.sensor_kind)
    survey = set_sensor_kind(session, survey_id, kind, user.id, f"declared by {user.username}")
    return SurveyPublic.model_validate(survey)


def declared(sensor: DeclaredSensor | None) -> SensorKind | None:
    return None if sensor is None else SensorKind(sensor)


@router.post(
    "/upload",
    response_model=SurveyPublic,
    status_code=201,
    responses=errors(403, 413, 422),
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/octet-stream": {"schema": {"type": "string"}}},
        }
    },
)
async def upload_survey(
    request: Request,
    user: Annotator,
    session: SessionDep,
    settings: SettingsDep,
    filename: Annotated[FileName, Query(description="survey.laz, or drive.zip")],
    format: str | None = Query(None, description="reader name; detected when absent"),
    name: str | None = Query(None, min_length=1, max_length=255),
    sensor: DeclaredSensor | None = Query(None, description=SENSOR_HELP),
) -> SurveyPublic:
    """Upload a .las/.laz map or a .zip of a KITTI-raw / SemanticKITTI / simulator folder as the
    raw request body (annotator role); stored under the surveys folder and registered."""
    suffix = check_upload_name(filename)
    limit_mb = settings.max_upload_mb
    folder = settings.surveys_dir.resolve() / uuid.uuid4().hex
    folder.mkdir(parents=True)
    try:
        if suffix == ".zip":
            archive = folder / ".upload.zip"
            size = await receive_upload(request, archive, filename, limit_mb)
            source = await run_in_threadpool(
                extract_zip, archive, source_of_upload(folder, filename), filename, limit_mb
            )
        else:
            source = source_of_upload(folder, filename)
            size = await receive_upload(request, source, filename, limit_mb)
        survey = await run_in_threadpool(
            import_source,
            session,
            source,
            format,
            name or Path(filename).stem,
            user.id,
            "survey.upload",
            sensor=declared(sensor),
            filename=filename,
            bytes=size,
        )
    except InputError as exc:
        remove_tree(folder)
        # name the file as the user knows it, not by the server's folder
        message = exc.message.replace(str(source_of_upload(folder, filename)), filename)
        raise InputError(None, message) from exc
    except BaseException:
        remove_tree(folder)
        raise
    return SurveyPublic.model_validate(survey)


def source_of_upload(folder: Path, filename: str) -> Path:
    """Where an upload lies on the server: the file itself, or the folder a zip unpacks to."""
    return folder / "data" if filename.lower().endswith(".zip") else folder / filename


def upload_folder(surveys_dir: Path, source_path: str) -> Path | None:
    """The `surveys_dir/<uuid>` folder an upload made that holds SOURCE_PATH, or None: files
    anywhere else are never deleted."""
    root = surveys_dir.resolve()
    source = Path(source_path)
    if not source.is_absolute() or not source.is_relative_to(root) or source == root:
        return None
    folder = root / source.relative_to(root).parts[0]
    if not UPLOAD_FOLDER.match(folder.name) or folder.is_symlink() or not folder.is_dir():
        return None
    return folder


@router.delete("/{survey_id}", status_code=204, responses=errors(403, 404, 409))
def remove_survey(
    survey_id: Id, user: Reviewer, session: SessionDep, settings: SettingsDep
) -> Response:
    """Delete a survey with its frames, labels, decisions and models (reviewer role); an
    uploaded survey's files go too, files imported from elsewhere stay."""
    survey = get_survey(session, survey_id)
    folder = upload_folder(settings.surveys_dir, survey.source_path)
    if folder is not None and surveys_using(session, folder, exclude=survey_id):
        folder = None  # another survey was imported from the same upload
    delete_survey(
        session, survey_id, user.id, files_deleted=None if folder is None else str(folder)
    )
    if folder is not None:
        remove_tree(folder)
    return Response(status_code=204)
