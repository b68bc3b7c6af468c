"""Clutter jobs of the web app: `run:clutter` runs the pipeline, writes the command-line
contract's files and puts everything it removed up for review; `clutter:recompute` rebuilds the
cleaned and removed maps from the reviewers' decisions.

A review unit ("instance") is what a reviewer can judge as one object in one frame:

- a camera instance (a depth layer of a mask component, `instances.py`) owns its own points
  and what the 3D expansion removed with it: the other removed points of a cluster it seeded
  (the cluster's main instance takes them) and masked ground-level points within `halo_radius`
  of its removed points (wheels, feet), as the expansion itself decides;
- every removed point no camera instance owns (free-space evidence, a moving track, a
  classified object carried out of the camera view) is grouped by its frame cluster, or, at
  ground level, by connected `cluster_voxel` voxels. Its class is the camera class of its track
  when the camera ever classified it, else "free-space" (or "padded-mask": the paper's padded
  masks with `expansion="pad"`).

Per frame the run writes `instances/<frame>.npz` (per point: `instance`, int32, -1 none;
`removed`, the pipeline's own flag; `in_view`) and `instances/<frame>/<index>.png` (the image
crop around the instance with its mask component tinted in its class colour and its points
dotted, white where the pipeline removes them, black where it keeps them; for instances outside
the image a top view of the frame around it, its points red / cyan).
The mask images lie in the run's folder: recompute finds the membership of the instances in
the store from their `mask_path`, so the rows and the files cannot come from different runs.
A decision applies to all points of its instance: approved -> removed, rejected -> kept,
pending -> the pipeline's flag.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree
from sqlmodel import Session

from app.core.errors import ConfigError, ConflictError, InputError
from app.core.settings import Settings
from app.geometry.projection import pixel_indices, project
from app.io import open_survey
from app.io.survey import Camera, Frame, Survey
from app.jobs.memory import (
    MEAN_RAY_M,
    SENSOR_REACH_M,
    MemoryEstimate,
    dufomap_mb,
    extent_text,
    frame_grid_mb,
    points_mb,
    survey_text,
)
from app.jobs.registry import JobContext, task
from app.jobs.task_config import refuse_model_path, validated
from app.pipelines.clutter.accumulate import accumulate
from app.pipelines.clutter.clusters import voxel_components
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.fusion import FrameEvidence, track_decisions
from app.pipelines.clutter.instances import mask_components
from app.pipelines.clutter.pipeline import ClutterPipeline, ClutterResult
from app.pipelines.clutter.run import (
    reference_metrics,
    run_clutter,
    write_clutter_outputs,
    write_maps,
)
from app.pipelines.clutter.segmenter import (
    CLUTTER_CLASSES,
    CLUTTER_COLORS,
    CachedSegmenter,
    ESPNetv2Segmenter,
)
from app.pipelines.outputs import write_frame_labels, write_report
from app.store import clutter_review
from app.store.models import Decision
from app.store.surveys import get_survey, survey_footprint

FREE_SPACE = "free-space"
PADDED_MASK = "padded-mask"
CROP_PAD_PX = 16  # context around an instance's pixels in its mask image
CLUTTER_BYTES_PER_POINT = 150.0  # per-frame evidence, maps, review units (measured: ~100)
SEGMENTER_MB = 700.0  # ESPNetv2 and torch's buffers (measured: ~640 MB on SemanticKITTI 04)
TOP_VIEW_PX = 256  # side of the top view of an instance outside the image
# point colours: on the image (over the class tint) and on the top view (over grey points)
IMAGE_RGB = {True: (255, 255, 255), False: (0, 0, 0)}  # removed by the pipeline / kept
TOP_RGB = {True: (255, 40, 40), False: (0, 230, 230)}

# share of the job's progress bar per pipeline stage: (start, span)
_STAGES = {
    "segmentation": (0.0, 0.3),
    "frames": (0.3, 0.25),
    "free space": (0.55, 0.1),
    "tracking": (0.65, 0.0),
    "done": (0.65, 0.0),
}


# --- run:clutter --------------------------------------------------------------------------


def check_run_config(config: dict[str, Any], settings: Settings) -> None:
    """Refuse a bad `run:clutter` config when the job is queued (422), not in the worker."""
    clutter_config(config)


def estimate_run(session: Session, survey: int | None, config: dict[str, Any]) -> MemoryEstimate:
    """run:clutter's memory: its point arrays, a frame's ground grid, the segmentation
    network, DUFOMap's octree (measured peak on SemanticKITTI 04, 1,234,476 points, defaults:
    1,060 MB; this estimate: about 1,600 MB)."""
    cfg = clutter_config(config)
    if survey is None:
        return MemoryEstimate("no survey")
    footprint = survey_footprint(session, survey)
    reach = 2 * SENSOR_REACH_M
    estimate = MemoryEstimate(survey_text(footprint))
    estimate.add(
        "survey_id",
        points_mb(footprint, CLUTTER_BYTES_PER_POINT),
        f"{CLUTTER_BYTES_PER_POINT:.0f} bytes per point",
    )
    estimate.add(
        "config.ground_cell",
        frame_grid_mb(cfg.ground_cell),
        f"{cfg.ground_cell:g} m ground cells over a frame's {reach:.0f} x {reach:.0f} m",
    )
    if cfg.use_camera:
        estimate.add("config.use_camera", SEGMENTER_MB, "the segmentation network")
    if cfg.use_free_space:
        estimate.add(
            "config.dufomap_resolution",
            dufomap_mb(footprint, cfg.dufomap_resolution),
            f"{cfg.dufomap_resolution:g} m free-space voxels over {extent_text(footprint)}, "
            f"rays of about {MEAN_RAY_M:.0f} m",
        )
    return estimate


def check_recompute_config(config: dict[str, Any], settings: Settings) -> None:
    if config:
        raise ConfigError(f"config.{next(iter(config))}", "clutter:recompute takes no options")


@task(clutter_review.RUN_KIND, check=check_run_config, estimate=estimate_run)
def run_clutter_task(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """The pipeline on the job's survey, its contract files in the workdir, and its instances
    (each pending) in the store in place of the previous run's."""
    cfg = clutter_config(config)
    survey = _open_survey(context)
    camera = ClutterPipeline(cfg).camera(survey)  # None: no images to segment
    segmenter = None if camera is None else ESPNetv2Segmenter(context.settings.weights_dir)
    result, cached, segmentation_s = run_clutter(
        survey,
        cfg,
        segmenter,
        _pipeline_progress(context),
        context.settings.cache_dir / "segmentation",
    )
    context.progress(0.7, "writing the cleaned map")
    out = context.workdir
    report = write_clutter_outputs(survey, out, cfg, result, cached, segmentation_s)
    context.progress(0.8, "instances for review")
    rows = write_review_units(survey, result, cfg, camera, cached, out / "instances", context)
    with Session(context.engine) as session:
        clutter_review.replace_instances(
            session, survey_id(context), rows, context.user_id, context.job_id
        )
    classes: dict[str, int] = {}
    for row in rows:
        classes[row["class_name"]] = classes.get(row["class_name"], 0) + 1
    counts = {**report["counts"], "instances": len(rows), "instances_per_class": classes}
    report["counts"] = counts
    report_path = write_report(out, report)
    context.progress(1.0, f"{len(rows)} instances to review")
    files = {name: str((out / path).resolve()) for name, path in report["files"].items()}
    files["labels"] = str((out / "labels").resolve())
    files["instances"] = str((out / "instances").resolve())
    files["report"] = str(report_path.resolve())
    return {
        "files": files,
        "report": files["report"],
        "counts": counts,
        "metrics": report.get("metrics"),
    }


def clutter_config(config: dict[str, Any]) -> ClutterConfig:
    """The job config as a ClutterConfig; an unknown key or a bad value names the field."""
    config = dict(config or {})
    refuse_model_path(config)
    unknown = sorted(set(config) - set(ClutterConfig.model_fields))
    if unknown:
        known = ", ".join(ClutterConfig.model_fields)
        raise ConfigError(f"config.{unknown[0]}", f"unknown field; known: {known}")
    return validated(ClutterConfig, config)


def survey_id(context: JobContext) -> int:
    if context.survey_id is None:
        raise ConfigError("survey_id", "a clutter job needs a survey")
    return context.survey_id


def _open_survey(context: JobContext) -> Survey:
    with Session(context.engine) as session:
        record = get_survey(session, survey_id(context))
        source, fmt = record.source_path, record.format
    return open_survey(Path(source), fmt)


def _pipeline_progress(context: JobContext) -> Callable[[str, float], None]:
    def report(stage: str, fraction: float) -> None:
        start, span = _STAGES.get(stage, (0.65, 0.0))
        context.progress(start + span * fraction, stage)

    return report


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
    context: JobContext | None = None,
) -> list[dict[str, Any]]:
    """Per frame the membership npz and the instances' mask images; returns the store rows."""
    folder.mkdir(parents=True, exist_ok=True)
    moving = movable = track_class = None
    if result.tracks is not None:
        moving, movable = track_decisions(result.tracks, config)
        track_class = np.where(movable, result.tracks.camera_class, 0)
    rows: list[dict[str, Any]] = []
    frames = list(survey.frames)
    for i, frame in enumerate(frames):
        if context is not None:
            context.progress(0.8 + 0.2 * i / max(len(frames), 1), "instances for review")
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
            tint = _class_colour(units.class_names[k])
            picture = _crop(
                image, components, int(component[k]), tint, bbox, row, col, mine, removed
            )
        else:
            picture = _top_view(xyz, mine, removed)
        _write_png(path, picture)
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


def _crop(
    image: np.ndarray,
    components: np.ndarray | None,
    component: int,
    tint: np.ndarray,
    bbox: list[int],
    row: np.ndarray,
    col: np.ndarray,
    mine: np.ndarray,  # (M,) indices of the instance's points
    removed: np.ndarray,
) -> np.ndarray:
    """The image around the instance: its mask component tinted in its class colour, its
    points dotted."""
    height, width = image.shape[:2]
    u0, v0 = max(bbox[0] - CROP_PAD_PX, 0), max(bbox[1] - CROP_PAD_PX, 0)
    u1, v1 = min(bbox[2] + CROP_PAD_PX, width - 1), min(bbox[3] + CROP_PAD_PX, height - 1)
    crop = image[v0 : v1 + 1, u0 : u1 + 1].astype(np.float32)
    if components is not None and component >= 0:
        on = components[v0 : v1 + 1, u0 : u1 + 1] == component
        crop[on] = 0.5 * crop[on] + 0.5 * tint.astype(np.float32)
    crop = crop.astype(np.uint8)
    dots = mine[row[mine] >= 0]
    colours = np.where(removed[dots, None], IMAGE_RGB[True], IMAGE_RGB[False]).astype(np.uint8)
    crop[row[dots] - v0, col[dots] - u0] = colours
    return crop


def _class_colour(name: str) -> np.ndarray:
    """The overlay colour of a clutter class (white for the groups without a mask)."""
    if name in CLUTTER_CLASSES:
        return CLUTTER_COLORS[CLUTTER_CLASSES.index(name) + 1]
    return np.array((255, 255, 255), dtype=np.uint8)


def _top_view(xyz: np.ndarray, mine: np.ndarray, removed: np.ndarray) -> np.ndarray:
    """A top view of the instance (`mine`: its point indices) and its surroundings, for
    instances outside the image."""
    own = xyz[mine, :2]
    centre = (own.min(axis=0) + own.max(axis=0)) / 2
    half = max(float(np.ptp(own, axis=0).max()) / 2 + 2.0, 4.0)
    scale = TOP_VIEW_PX / (2 * half)
    picture = np.zeros((TOP_VIEW_PX, TOP_VIEW_PX, 3), dtype=np.uint8)

    def pixels(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u = ((points[:, 0] - centre[0] + half) * scale).astype(np.int64)
        v = ((centre[1] + half - points[:, 1]) * scale).astype(np.int64)  # north up
        inside = (u >= 0) & (u < TOP_VIEW_PX) & (v >= 0) & (v < TOP_VIEW_PX)
        return v[inside], u[inside], inside

    v, u, _ = pixels(xyz[:, :2])
    picture[v, u] = 100
    v, u, inside = pixels(own)
    colours = np.where(removed[mine][inside, None], TOP_RGB[True], TOP_RGB[False])
    for dv in (-1, 0, 1):  # 3 x 3 dots: a few points must still show
        for du in (-1, 0, 1):
            picture[np.clip(v + dv, 0, TOP_VIEW_PX - 1), np.clip(u + du, 0, TOP_VIEW_PX - 1)] = (
                colours
            )
    return picture


def _write_png(path: Path, rgb: np.ndarray) -> None:
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"could not encode the mask image {path}")
    path.write_bytes(png.tobytes())


# --- clutter:recompute --------------------------------------------------------------------


@task(clutter_review.RECOMPUTE_KIND, check=check_recompute_config)
def recompute_clutter(context: JobContext, config: dict[str, Any]) -> dict[str, Any]:
    """The cleaned and removed maps (and labels) of the survey from the reviewers' decisions
    on the instances of its current clutter run."""
    check_recompute_config(config, context.settings)
    started = time.perf_counter()
    sid = survey_id(context)
    with Session(context.engine) as session:
        record = get_survey(session, sid)
        source, fmt = record.source_path, record.format
        decisions = clutter_review.review_decisions(session, sid)
        run = clutter_review.run_folder_of([d[3] for d in decisions])
        if run is None:
            job = clutter_review.latest_run(session, sid)
            if job is None or "instances" not in job.result.get("files", {}):
                raise ConflictError(f"survey {sid} has no clutter run to review; run clutter")
            run = Path(job.result["files"]["instances"]).parent
    survey = open_survey(Path(source), fmt)
    run_config = _run_config(run)
    context.progress(0.05, "applying the decisions")
    removed, in_view, pipeline_removed = apply_decisions(survey, run / "instances", decisions)
    context.progress(0.4, "accumulating the maps")
    out = context.workdir
    write_frame_labels(
        out, {f.frame_id: r.astype(np.uint8) for f, r in zip(survey.frames, removed, strict=True)}
    )
    kept_map, removed_map = accumulate(survey, removed, run_config.voxel_dedup)
    context.progress(0.8, "writing the maps")
    files = {
        name: str((out / path).resolve())
        for name, path in write_maps(out, kept_map, removed_map).items()
    }
    tally = {d.value: 0 for d in Decision}
    for _, _, decision, _ in decisions:
        tally[decision.value] += 1
    counts = {
        "frames": len(removed),
        "points": int(sum(len(r) for r in removed)),
        "removed_points": int(sum(int(r.sum()) for r in removed)),
        "pipeline_removed_points": pipeline_removed,
        "map_points": int(len(kept_map.xyz)),
        "instances": len(decisions),
        "decisions": tally,
    }
    report: dict[str, Any] = {
        "pipeline": "clutter",
        "recomputed_from": str(run),
        "survey": {"name": survey.name, "format": survey.format, "source": str(survey.source)},
        "config": run_config.model_dump(),
        "counts": counts,
        "files": {name: Path(path).name for name, path in files.items()},
    }
    metrics = reference_metrics(survey, removed, in_view)
    if metrics is not None:
        report["metrics"] = metrics
    report["timings"] = {"total": round(time.perf_counter() - started, 3)}
    report_path = write_report(out, report)
    context.progress(1.0, f"{counts['removed_points']} points removed after review")
    files["labels"] = str((out / "labels").resolve())
    files["report"] = str(report_path.resolve())
    return {"files": files, "report": files["report"], "counts": counts, "metrics": metrics}


def _run_config(run: Path) -> ClutterConfig:
    path = run / "report.json"
    try:
        return ClutterConfig.model_validate(json.loads(path.read_text())["config"])
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(path, f"is not the report of a clutter run ({exc})") from None


def apply_decisions(
    survey: Survey,
    folder: Path,
    decisions: list[tuple[str, int, Decision, str | None]],
) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """Per frame the removed flags after review and the camera-view flags, and how many points
    the pipeline itself removed: approved instances go, rejected ones stay, pending ones keep
    the pipeline's flag."""
    verdict = {Decision.approved: 1, Decision.rejected: 0, Decision.pending: -1}
    by_frame: dict[str, list[tuple[int, int]]] = {}
    for frame_id, index, decision, _ in decisions:
        by_frame.setdefault(frame_id, []).append((index, verdict[decision]))
    removed, in_view = [], []
    pipeline_removed = 0
    for frame in survey.frames:
        path = folder / f"{frame.frame_id}.npz"
        try:
            with np.load(path) as data:
                owner, flags, view = data["instance"], data["removed"], data["in_view"]
        except (OSError, KeyError, ValueError) as exc:
            raise InputError(path, f"unreadable review membership ({exc})") from None
        if frame.point_count is not None and len(owner) != frame.point_count:
            raise InputError(
                path, f"{len(owner)} points, frame {frame.frame_id} has {frame.point_count}"
            )
        state = np.full(int(owner.max(initial=-1)) + 1, -1, dtype=np.int8)
        if frame.frame_id in by_frame:
            index, value = np.array(by_frame.pop(frame.frame_id)).T
            if index.max() >= len(state):
                raise InputError(path, f"has no instance {int(index.max())} of the store")
            state[index] = value
        gone = flags.astype(bool, copy=True)
        owned = owner >= 0
        choice = state[owner[owned]]
        gone[owned] = np.where(choice < 0, gone[owned], choice == 1)
        pipeline_removed += int(flags.sum())
        removed.append(gone)
        in_view.append(view.astype(bool))
    if by_frame:
        raise InputError(folder, f"no frame {next(iter(by_frame))} in the survey")
    return removed, in_view, pipeline_removed
