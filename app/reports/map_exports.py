"""The maps of the newest clutter or phantom run in the forms other mapping tools read: LAZ with
the survey's coordinate system, both maps joined into one classified LAZ (ASPRS classes as
`app.io.asprs` maps them, the pipeline's labels in `mmsclean_label`), and PCD with a label field.

A survey's CRS is what its imported LAS / LAZ header records (the store keeps none of its own);
other formats record none, and the exports say so rather than guess one. The LAZ files are
joined and given the CRS by copying their compressed chunks (`LasAppender`): no point is
re-encoded. The PCD is written a LAS chunk at a time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from sqlmodel import Session

from app.core.errors import InputError, NotFoundError
from app.core.labels import PILLAR_CLASS_NAMES, ClutterLabel
from app.core.settings import Settings
from app.io.las import LasAppender, las_crs, las_point_count, read_las_chunks
from app.io.pcd import write_labelled_pcd
from app.reports.exports import removal_map, removal_maps, remover_of
from app.store.models import Job, Survey


def survey_crs(survey: Survey) -> tuple[str | None, str]:
    """(WKT or None, a line saying where it came from or why there is none)."""
    if survey.format != "las":
        return None, f"a {survey.format} survey records no CRS (only LAS / LAZ headers do)"
    try:
        return las_crs(Path(survey.source_path))
    except InputError as exc:
        return None, f"the survey's source header could not be read for its CRS ({exc})"


def map_with_crs(
    session: Session, settings: Settings, survey: Survey, which: str, source: str, dest: Path
) -> tuple[Path, Job, str]:
    """The `which` map of the newest run of `source` (`removal_map`), as DEST with the survey's
    CRS when it has one, else the run's own file; and the CRS line."""
    path, job = removal_map(session, settings, survey, which, source)
    wkt, note = survey_crs(survey)
    if wkt is None:
        return path, job, note
    join([path], dest, wkt)
    return dest, job, note


def write_classified_laz(
    session: Session, settings: Settings, survey: Survey, source: str, dest: Path
) -> tuple[Job, int, str]:
    """The run's cleaned and removed maps joined into DEST, with the survey's CRS when it has
    one; (the run, its points, the CRS line)."""
    maps, job = removal_maps(session, settings, survey, source)
    wkt, note = survey_crs(survey)
    return job, join(list(maps.values()), dest, wkt), note


def join(parts: list[Path], dest: Path, wkt: str | None) -> int:
    appender = LasAppender(dest, wkt)
    try:
        for part in parts:
            appender.append(part)
        return appender.close()
    except BaseException:
        appender.abort()
        raise


def label_meaning(job: Job) -> str:
    """What `mmsclean_label` (the PCD's `label`) means in the run's maps."""
    if remover_of(job) == "clutter":
        names = [c.name.lower() for c in ClutterLabel]
    else:
        names = list(PILLAR_CLASS_NAMES)
    return ", ".join(f"{i} {name}" for i, name in enumerate(names))


def write_map_pcd(
    session: Session,
    settings: Settings,
    survey: Survey,
    source: str,
    which: tuple[str, ...],
    dest: Path,
) -> tuple[Job, int]:
    """The run's maps named in `which` ("cleaned", "removed") as one binary PCD: x y z (float32,
    from the survey's origin), intensity (the LAS 16-bit value), label (mmsclean's per-point
    label, `mmsclean_label`); (the run, its points)."""
    maps, job = removal_maps(session, settings, survey, source)
    if not set(which) & set(maps):
        raise NotFoundError(f"{job.kind} job {job.id} wrote no {' or '.join(which)} map")
    parts = [maps[w] for w in which if w in maps]
    origin = np.asarray(survey.origin, dtype=np.float64)
    total = sum(las_point_count(p) for p in parts)
    note = survey_crs(survey)[1]
    comments = [
        f"mmsclean {' and '.join(w for w in which if w in maps)} map of survey {survey.name!r} "
        f"(id {survey.id}), {job.kind} job {job.id}",
        "origin {:.3f} {:.3f} {:.3f}: add it to x y z for the world coordinates".format(*origin),
        f"label: mmsclean's label ({label_meaning(job)})",
        f"intensity: the LAS 16-bit intensity; CRS: {note}",
    ]

    def pieces():
        for part in parts:
            for _, cloud in read_las_chunks(part):
                label = cloud.extra.get("mmsclean_label")
                if label is None:
                    raise InputError(part, "has no mmsclean_label dimension")
                intensity = cloud.intensity
                if intensity is None:
                    intensity = np.zeros(len(cloud.xyz), np.float32)
                yield cloud.xyz - origin, intensity, label

    write_labelled_pcd(dest, total, pieces(), comments)
    return job, total
