"""The combined maps: what the newest clutter run and the newest phantom run removed, both left
out of one cleaned map (issue 20: exports cover clutter, phantom, and both combined).

Both pipelines write every map point with `source_frame` and `source_index` (the survey frame's
position and the point's index among that frame's points), so a point removed by either run is
known by that key. The phantom run's removed keys are read first (removed points are few); the
clutter run's cleaned map is then streamed a chunk at a time without them, and the removed map
is the clutter run's removed points plus the phantom run's that are not among them. Each point
keeps the record its run wrote (its label, ASPRS class, intensity). Memory: the removed keys.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np
from sqlmodel import Session

from app.core.settings import Settings
from app.io.las import LasAppender, read_las_chunks, write_laz
from app.io.survey import PointCloud
from app.reports.exports import removal_maps
from app.reports.map_exports import survey_crs
from app.store.models import Job, Survey


def point_keys(cloud: PointCloud) -> np.ndarray:
    """(n,) uint64 frame << 32 | index of a map chunk's points."""
    frame = cloud.extra["source_frame"].astype(np.uint64)
    return (frame << np.uint64(32)) | cloud.extra["source_index"].astype(np.uint64)


def removed_keys(path: Path | None) -> np.ndarray:
    """Sorted keys of every point of a map file (none for no file), a chunk at a time."""
    if path is None:
        return np.zeros(0, dtype=np.uint64)
    parts = [np.unique(point_keys(cloud)) for _, cloud in read_las_chunks(path)]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.uint64)


def _outside(keys: np.ndarray, sorted_keys: np.ndarray) -> np.ndarray:
    if not len(sorted_keys):
        return np.ones(len(keys), dtype=bool)
    at = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[at] != keys


def _filtered(path: Path | None, drop: np.ndarray) -> Iterator[PointCloud]:
    """The chunks of a map file without the points whose key is in `drop`."""
    if path is None:
        return
    for _, cloud in read_las_chunks(path):
        keep = _outside(point_keys(cloud), drop)
        if keep.any():
            yield _subset(cloud, keep)


def _subset(cloud: PointCloud, keep: np.ndarray) -> PointCloud:
    def pick(values: np.ndarray | None) -> np.ndarray | None:
        return None if values is None else values[keep]

    extra = {name: values[keep] for name, values in cloud.extra.items()}
    return PointCloud(cloud.xyz[keep], pick(cloud.intensity), pick(cloud.time), extra)


def write_combined_map(
    session: Session, settings: Settings, survey: Survey, which: str, dest: Path
) -> tuple[list[Job], int, str]:
    """The combined `which` ("cleaned" / "removed") map as DEST with the survey's CRS when it
    has one; (the two runs, its points, the CRS line)."""
    clutter, clutter_job = removal_maps(session, settings, survey, "clutter")
    phantom, phantom_job = removal_maps(session, settings, survey, "phantom")
    if which == "cleaned":
        pieces = [_filtered(clutter.get("cleaned"), removed_keys(phantom.get("removed")))]
    else:
        pieces = [
            _filtered(clutter.get("removed"), np.zeros(0, dtype=np.uint64)),
            _filtered(phantom.get("removed"), removed_keys(clutter.get("removed"))),
        ]
    reference = clutter.get("cleaned") or clutter.get("removed")
    with laspy.open(reference) as reader:
        offset = np.asarray(reader.header.offsets, dtype=np.float64)
    wkt, crs = survey_crs(survey)
    appender = LasAppender(dest, wkt)
    try:
        with tempfile.TemporaryDirectory(dir=dest.parent) as tmp:
            part = Path(tmp) / "part.laz"
            for chunks in pieces:
                for cloud in chunks:
                    _write_part(part, cloud, offset)
                    appender.append(part)
                    part.unlink()
        count = appender.close()
    except BaseException:
        appender.abort()
        raise
    return [clutter_job, phantom_job], count, crs


def _write_part(path: Path, cloud: PointCloud, offset: np.ndarray) -> None:
    extra = cloud.extra
    write_laz(
        path,
        cloud.xyz,
        mmsclean_label=extra.get("mmsclean_label"),
        classification=extra.get("classification"),
        source_frame=extra["source_frame"],
        source_index=extra["source_index"],
        intensity=cloud.intensity,
        gps_time=cloud.time,
        offset=offset,
    )
