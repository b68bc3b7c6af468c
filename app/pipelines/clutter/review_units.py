"""Review units of a clutter run: what a reviewer can judge as one object in one frame.

- a camera instance (a depth layer of a mask component, `instances.py`) owns its own points
  and what the 3D expansion removed with it: the other removed points of a cluster it seeded
  (the cluster's main instance takes them) and masked ground-level points within `halo_radius`
  of its removed points (wheels, feet), as the expansion itself decides;
- every removed point no camera instance owns (free-space evidence, a moving track, a
  classified object carried out of the camera view) is grouped by its frame cluster, or, at
  ground level, by connected `cluster_voxel` voxels. Its class is the camera class of its track
  when the camera ever classified it, else "free-space" (or "padded-mask": the paper's padded
  masks with `expansion="pad"`).

Per frame a run writes `<frame>.npz` (per point: `instance`, int32, -1 none; `removed`, the
pipeline's own flag; `in_view`) and `<frame>/<index>.png`, each instance's mask image
(`overlays.py`). The store rows are plain dicts: the clutter job stores them. After review,
`apply_decisions` reads the membership back, applies the reviewers' corrections of it
(`review_corrections`: points taken out of an instance, missed objects added) and their verdicts.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from app.core.errors import InputError
from app.geometry.projection import pixel_indices, project
from app.io.survey import Camera, Frame, Survey
from app.pipelines.clutter.clusters import voxel_components
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.fusion import FrameEvidence, track_decisions
from app.pipelines.clutter.instances import mask_components
from app.pipelines.clutter.overlays import class_colour, mask_crop, top_view, write_png
from app.pipelines.clutter.pipeline import ClutterResult
from app.pipelines.clutter.review_corrections import MembershipCorrection, corrected_membership
from app.pipelines.clutter.segmenter import CLUTTER_CLASSES, CachedSegmenter

FREE_SPACE = "free-space"
PADDED_MASK = "padded-mask"
MOVED_TRACK = "moved-track"


@dataclass
class FrameInstances:
    """The review units of one frame: each point's owner, each instance's store fields."""

    owner: np.ndarray  # (N,) int32 instance index, -1 = none
    class_names: list[str]
    camera_count: int  # instances below this index are camera instances
    track_id: np.ndarray  # (K,) int64, -1 = untracked
    moving: list[bool | None]

    @property
    def count(self) -> int:
        return len(self.class_names)


def _dominant(keys: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """(count,) the most frequent value per key (values >= 0), -1 for keys with none."""
    out = np.full(count, -1, dtype=np.int64)
    if len(keys) == 0:
        return out
    span = int(values.max()) + 1
    pairs, tally = np.unique(keys.astype(np.int64) * span + values, return_counts=True)
    key, value = pairs // span, pairs % span
    order = np.lexsort((-tally, key))
    key, value = key[order], value[order]
    first = np.ones(len(key), dtype=bool)
    first[1:] = key[1:] != key[:-1]
    out[key[first]] = value[first]
    return out


def frame_instances(
    xyz: np.ndarray,
    removed: np.ndarray,
    evidence: FrameEvidence,
    cluster_track: np.ndarray | None,
    track_moving: np.ndarray | None,
    track_class: np.ndarray | None,
    config: ClutterConfig,
) -> FrameInstances:
    """Which points each review unit of the frame owns (see the module docstring)."""
    n = len(removed)
    owner = (
        np.full(n, -1, dtype=np.int32)
        if evidence.instance is None
        else evidence.instance.astype(np.int32, copy=True)
    )
    mask_class = np.zeros(n, np.uint8) if evidence.mask_class is None else evidence.mask_class
    cluster = evidence.cluster
    clustered = cluster >= 0
    clusters = int(cluster.max(initial=-1)) + 1
    seeds = owner >= 0
    camera_count = int(owner.max(initial=-1)) + 1
    camera_class = np.zeros(camera_count, dtype=np.uint8)
    camera_class[owner[seeds]] = mask_class[seeds]
    # removed points of clusters the instances seeded go with the cluster's main instance
    main = _dominant(cluster[seeds & clustered], owner[seeds & clustered], clusters)
    grow = removed & ~seeds & clustered
    owner[grow] = main[cluster[grow]]
    # masked ground-level points near an instance's removed points (wheels, feet)
    loose = removed & (owner < 0) & ~clustered & (mask_class > 0)
    anchor = removed & (owner >= 0)
    if config.halo_radius > 0 and loose.any() and anchor.any():
        distance, nearest = cKDTree(xyz[anchor]).query(
            xyz[loose], k=1, distance_upper_bound=config.halo_radius, workers=-1
        )
        near = np.isfinite(distance)
        owner[np.flatnonzero(loose)[near]] = owner[np.flatnonzero(anchor)[nearest[near]]]
    # the other removed points: their cluster, or connected voxels at ground level
    rest = removed & (owner < 0)
    group_key = np.full(n, -1, dtype=np.int64)
    group_key[rest & clustered] = cluster[rest & clustered]
    ground = rest & ~clustered
    if ground.any():
        group_key[ground] = clusters + voxel_components(xyz[ground], config.cluster_voxel)
    groups, inverse = np.unique(group_key[rest], return_inverse=True)
    owner[rest] = camera_count + inverse.reshape(-1)
    count = camera_count + len(groups)

    owned = owner >= 0
    size = np.bincount(owner[owned], minlength=count)
    point_track = np.full(n, -1, dtype=np.int64)
    if cluster_track is not None and len(cluster_track):
        point_track[clustered] = cluster_track[cluster[clustered]]
    tracked = owned & (point_track >= 0)
    track = _dominant(owner[tracked], point_track[tracked], count)
    free = np.bincount(owner[owned & evidence.free], minlength=count)
    padded = np.bincount(owner[owned & evidence.padded], minlength=count)
    names = [CLUTTER_CLASSES[c - 1] for c in camera_class.tolist()]
    for k in range(camera_count, count):  # one name per group, not per point
        cls = 0 if track[k] < 0 or track_class is None else int(track_class[track[k]])
        if cls > 0:
            names.append(CLUTTER_CLASSES[cls - 1])
        elif config.expansion == "pad" and padded[k] > free[k]:
            names.append(PADDED_MASK)
        elif (
            track[k] >= 0
            and track_moving is not None
            and track_moving[track[k]]
            and (2 * free[k] < size[k])
        ):
            names.append(MOVED_TRACK)  # an object nobody classed, moving by its surface
        else:
            names.append(FREE_SPACE)
    by_free = free >= config.min_free_fraction * np.maximum(size, 1)
    moving: list[bool | None] = []
    for k in range(count):
        if track[k] >= 0 and track_moving is not None:
            moving.append(bool(track_moving[track[k]]))
        else:
            moving.append(bool(by_free[k]) if config.use_free_space else None)
    return FrameInstances(owner, names, camera_count, track, moving)


def write_review_units(
    survey: Survey,
    result: ClutterResult,
    config: ClutterConfig,
    camera: Camera | None,
    cached: CachedSegmenter | None,
    folder: Path,
    progress: Callable[[float, str], object] | None = None,
    keep: np.ndarray | None = None,
) -> list[dict[str, Any]]:
    """Per frame of the result (or those at the positions `keep` lists: a tile's own) the
    membership npz and the instances' mask images; returns the store rows (plain dicts: the job
    puts them in the store). `progress(fraction, message)` sees each frame on the job's bar."""
    folder.mkdir(parents=True, exist_ok=True)
    moving = movable = track_class = None
    if result.tracks is not None:
        moving, movable = track_decisions(result.tracks, config)
        track_class = np.where(movable, result.tracks.camera_class, 0)
    rows: list[dict[str, Any]] = []
    numbers = result.frame_numbers
    if numbers is None:
        numbers = np.arange(len(result.frame_ids))
    positions = np.arange(len(numbers)) if keep is None else np.asarray(keep, dtype=np.int64)
    for n, i in enumerate(positions.tolist()):
        if progress is not None:
            progress(0.8 + 0.2 * n / max(len(positions), 1), "instances for review")
        frame = survey.frames[int(numbers[i])]
        xyz = frame.points().xyz
        cluster_track = None if result.tracks is None else result.tracks.cluster_track[i]
        units = frame_instances(
            xyz, result.removed[i], result.evidence[i], cluster_track, moving, track_class, config
        )
        np.savez_compressed(
            folder / f"{frame.frame_id}.npz",
            instance=units.owner,
            removed=result.removed[i],
            in_view=result.in_view[i],
        )
        rows += _frame_rows(frame, xyz, result.removed[i], units, camera, cached, folder)
    return rows


def _frame_rows(
    frame: Frame,
    xyz: np.ndarray,
    removed: np.ndarray,
    units: FrameInstances,
    camera: Camera | None,
    cached: CachedSegmenter | None,
    folder: Path,
) -> list[dict[str, Any]]:
    """Bounding boxes, mask images and store rows of one frame's instances."""
    if units.count == 0:
        return []
    out = folder / frame.frame_id
    out.mkdir(exist_ok=True)
    owner = units.owner
    image = components = None
    row = np.full(len(xyz), -1, dtype=np.int64)
    col = np.full(len(xyz), -1, dtype=np.int64)
    if camera is not None and camera.name in frame.image_paths and cached is not None:
        class_map = cached.lookup(frame.image_paths[camera.name])
        if class_map is not None:
            from app.io.images import read_rgb

            image = read_rgb(frame.image_paths[camera.name])
            components = mask_components(class_map)
            proj = project(xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)
            row[proj.in_image], col[proj.in_image] = pixel_indices(proj)
    seen = (owner >= 0) & (row >= 0)
    lo = np.full((units.count, 2), np.iinfo(np.int64).max)
    hi = np.full((units.count, 2), -1)
    pixels = np.stack([col, row], axis=1)
    np.minimum.at(lo, owner[seen], pixels[seen])
    np.maximum.at(hi, owner[seen], pixels[seen])
    component = np.full(units.count, -1, dtype=np.int64)
    if components is not None:
        seed = seen & (owner < units.camera_count)
        under = components[row[seed], col[seed]]
        on = under >= 0
        component = _dominant(owner[seed][on], under[on], units.count)
    order = np.argsort(owner, kind="stable")  # each instance's points: one slice of `order`
    starts = np.searchsorted(owner[order], np.arange(units.count + 1))
    rows = []
    for k in range(units.count):  # one image per instance
        mine = order[starts[k] : starts[k + 1]]
        bbox = None if hi[k, 0] < 0 else [*lo[k].tolist(), *hi[k].tolist()]
        path = out / f"{k}.png"
        if bbox is not None and image is not None:
            tint = class_colour(units.class_names[k])
            picture = mask_crop(
                image, components, int(component[k]), tint, bbox, row, col, mine, removed
            )
        else:
            picture = top_view(xyz, mine, removed)
        write_png(path, picture)
        rows.append(
            {
                "frame_id": frame.frame_id,
                "instance_index": k,
                "class_name": units.class_names[k],
                "point_count": len(mine),
                "mask_path": str(path.resolve()),
                "bbox": bbox,
                "moving": units.moving[k],
                "track_id": None if units.track_id[k] < 0 else int(units.track_id[k]),
            }
        )
    return rows


def apply_decisions(
    survey: Survey,
    folder: Path,
    verdicts: list[tuple[str, int, int]],
    corrections: dict[str, list[MembershipCorrection]] | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """Per frame the removed flags after review and the camera-view flags, and how many points
    the pipeline itself removed. `verdicts`: (frame id, instance index, verdict) with verdict 1
    (approved: its points go), 0 (rejected: they stay) or -1 (pending: the pipeline's flag);
    `corrections`: per frame id, the reviewers' corrections of the membership, in order."""
    by_frame = verdicts_by_frame(verdicts)
    corrections = corrections or {}
    removed, in_view = [], []
    pipeline_removed = 0
    for frame in survey.frames:
        reviewed = reviewed_frame(
            folder, frame.frame_id, frame.point_count, by_frame.pop(frame.frame_id, []),
            corrections.get(frame.frame_id, ()),
        )  # fmt: skip
        pipeline_removed += int(reviewed.pipeline_removed.sum())
        removed.append(reviewed.removed)
        in_view.append(reviewed.in_view)
    if by_frame:
        raise InputError(folder, f"no frame {next(iter(by_frame))} in the survey")
    return removed, in_view, pipeline_removed


def verdicts_by_frame(verdicts: list[tuple[str, int, int]]) -> dict[str, list[tuple[int, int]]]:
    """(frame id, instance index, verdict) grouped by frame id."""
    by_frame: dict[str, list[tuple[int, int]]] = {}
    for frame_id, index, verdict in verdicts:
        by_frame.setdefault(frame_id, []).append((index, verdict))
    return by_frame


@dataclass
class ReviewedFrame:
    """One frame's review membership with the verdicts applied."""

    owner: np.ndarray  # (N,) int32 instance index, -1 = none
    removed: np.ndarray  # (N,) bool after review
    pipeline_removed: np.ndarray  # (N,) bool, the pipeline's own flag
    in_view: np.ndarray  # (N,) bool


def reviewed_frame(
    folder: Path,
    frame_id: str,
    point_count: int | None,
    verdicts: list[tuple[int, int]],
    corrections: Sequence[MembershipCorrection] = (),
) -> ReviewedFrame:
    """The frame's membership (`folder/<frame>.npz`) with the reviewers' `corrections` and its
    (instance index, verdict) pairs applied: a frame at a time, so a caller holds one frame's
    arrays. `owner` is the corrected membership, `pipeline_removed` the run's own flags."""
    path = folder / f"{frame_id}.npz"
    try:
        with np.load(path) as data:
            owner, flags, view = data["instance"], data["removed"], data["in_view"]
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(path, f"unreadable review membership ({exc})") from None
    if point_count is not None and len(owner) != point_count:
        raise InputError(path, f"{len(owner)} points, frame {frame_id} has {point_count}")
    pipeline_flags = flags.astype(bool)
    # the run's instances and those the corrections add (an instance may have lost every point)
    size = max([int(owner.max(initial=-1)) + 1, *(c.instance_index + 1 for c in corrections)])
    if corrections:
        owner, flags = corrected_membership(owner, pipeline_flags, corrections)
    state = np.full(size, -1, dtype=np.int8)
    if verdicts:
        index, value = np.array(verdicts).T
        if index.max() >= len(state):
            raise InputError(path, f"has no instance {int(index.max())} of the store")
        state[index] = value
    flags = flags.astype(bool)
    gone = flags.copy()
    owned = owner >= 0
    choice = state[owner[owned]]
    gone[owned] = np.where(choice < 0, gone[owned], choice == 1)
    return ReviewedFrame(owner, gone, pipeline_flags, view.astype(bool))
