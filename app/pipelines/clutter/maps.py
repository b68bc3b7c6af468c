"""The clutter run's maps (the paper's accumulation step): every frame's kept and removed points,
posed into the world, written a frame at a time to `<prefix>.cleaned.laz` and
`<prefix>.removed.laz` (no prefix: the contract's names; a frame's part appended, then
dropped), so nothing holds a survey's points. With `voxel_dedup`, one kept point per voxel is
written, the first one in frame order, which drops the near-duplicates of many passes over the
same surface; the voxel grid is fixed by the maps' offset, so a tiled run's tiles share it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.geometry.voxels import voxel_indices
from app.io.asprs import CLUTTER_LABEL_TO_ASPRS, to_asprs
from app.io.las import LasAppender, write_laz
from app.io.survey import PointCloud, Survey
from app.pipelines.tiling import MAPS


def maps_offset(survey: Survey) -> np.ndarray:
    """The maps' LAS offset (and the dedup grid's origin): the first sensor position in whole
    metres, known before any point is read."""
    return np.floor(survey.frames[0].pose[:3, 3]) if survey.frames else np.zeros(3)


def write_frame_maps(
    folder: Path,
    prefix: str,
    survey: Survey,
    frames: np.ndarray,
    removed: list[np.ndarray],
    voxel_dedup: float | None,
    offset: tuple[float, float, float] | np.ndarray,
) -> dict:
    """The kept and removed points of the survey's frames `frames` (indices, with their
    per-point `removed` flags) as `folder/<prefix>.<map>.laz` (empty ones too); returns
    {map: file name} and "map_points": the kept points written. `offset` is the LAS
    offset (whole metres near the survey)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    offset = np.asarray(offset, dtype=np.float64)
    first = None
    if voxel_dedup:
        first = first_in_voxel(survey, frames, removed, voxel_dedup, offset)
    names = {kind: f"{prefix}.{kind}.laz" if prefix else f"{kind}.laz" for kind in MAPS}
    appenders = {kind: LasAppender(folder / names[kind]) for kind in MAPS}
    kept_points = 0
    try:
        for n, (k, gone) in enumerate(zip(np.asarray(frames).tolist(), removed, strict=True)):
            cloud = survey.frames[k].world_points()
            if len(cloud.xyz) != len(gone):
                raise ValueError(f"frame {survey.frames[k].frame_id}: {len(cloud.xyz)} points, "
                                 f"{len(gone)} decisions")  # fmt: skip
            gone = np.asarray(gone, dtype=bool)
            keep = ~gone if first is None else ~gone & first[n]
            kept_points += int(keep.sum())
            for kind, which, label in (("cleaned", keep, 0), ("removed", gone, 1)):
                if which.any():
                    part = folder / f"{prefix or 'map'}.{kind}.frame.laz"
                    _write_points(part, cloud, np.flatnonzero(which), k, label, offset)
                    appenders[kind].append(part)
                    part.unlink()
        maps: dict = {"map_points": kept_points}
        for kind in MAPS:
            if not appenders[kind].close():  # no point: the file is there all the same
                write_laz(folder / names[kind], np.zeros((0, 3)), offset=offset)
            maps[kind] = names[kind]
        return maps
    except BaseException:
        for appender in appenders.values():
            appender.abort()
        raise


def _write_points(
    path: Path, cloud: PointCloud, index: np.ndarray, frame: int, label: int, offset: np.ndarray
) -> None:
    labels = np.full(len(index), label, dtype=np.uint8)
    write_laz(
        path,
        cloud.xyz[index],
        mmsclean_label=labels,
        classification=to_asprs(labels, CLUTTER_LABEL_TO_ASPRS),
        source_frame=np.full(len(index), frame, dtype=np.uint32),
        source_index=index.astype(np.uint32),
        intensity=None if cloud.intensity is None else reflectance(cloud.intensity[index]),
        offset=offset,
    )


def reflectance(values: np.ndarray) -> np.ndarray:
    """Reflectance 0..1 to the LAS 16-bit range; values already above 1 are kept as they are."""
    values = np.asarray(values, dtype=np.float64)
    return values * 65535.0 if values.size and values.max() <= 1.0 else values


_HALF = 1 << 20  # voxel indices from the maps' offset within +-2^20 pack into one int64


def _voxel_key(ijk: np.ndarray) -> np.ndarray:
    """(N,) int64 key of voxel indices (N, 3), the same in every frame (unlike
    `geometry.voxels.voxel_keys`, whose keys hold within one call)."""
    if len(ijk) and int(np.abs(ijk).max()) >= _HALF:
        raise ValueError("voxel_dedup: the survey reaches over 2^20 voxels from the maps' "
                         "offset; use larger voxels")  # fmt: skip
    shifted = ijk.astype(np.int64) + _HALF
    return (shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2]


def first_in_voxel(
    survey: Survey,
    frames: np.ndarray,
    removed: list[np.ndarray],
    voxel: float,
    origin: np.ndarray,
) -> list[np.ndarray]:
    """Per frame, (N,) bool: the point is the first kept point of its voxel (frame order).
    One key per kept point is held."""
    keys = []
    for k, gone in zip(np.asarray(frames).tolist(), removed, strict=True):
        xyz = survey.frames[k].world_points().xyz
        keys.append(_voxel_key(voxel_indices(xyz[~np.asarray(gone, bool)], voxel, origin)))
    flat = np.concatenate(keys) if keys else np.zeros(0, dtype=np.int64)
    chosen = np.zeros(len(flat), dtype=bool)
    chosen[np.unique(flat, return_index=True)[1]] = True
    out, start = [], 0
    for gone, part in zip(removed, keys, strict=True):
        flags = np.zeros(len(gone), dtype=bool)
        flags[~np.asarray(gone, bool)] = chosen[start : start + len(part)]
        start += len(part)
        out.append(flags)
    return out
