"""The clutter pipeline, step by step (Lee et al. 2020, then past it):

1. segment each frame's camera image (people, riders, cars, trucks, buses, trams, motorcycles,
   bicycles), cached per frame;
2. project the frame's LiDAR points into the image, look up the masks (`masking.py`);
3. camera instances: mask components split at depth jumps (`instances.py`);
4. 3D expansion: instances grown to their frame's Euclidean cluster when an object of their
   class can be that large (`expansion.py`), or the paper's padded masks (`expansion="pad"`);
5. free-space evidence: every frame's rays into DUFOMap, ground-level flags kept only at the feet
   of free objects (`freespace.py`);
6. tracking: object-sized clusters linked across frames, their motion measured by registering
   each object onto its previous frame (`tracking.py`, `motion.py`), a person's by its lower
   body; loose pieces and tyres attached to their object (`clusters.object_hosts`); in clutter
   mode on a rotating scanner, each cluster's vehicle shape (`shapes.py`);
7. fusion by mode (`fusion.py`): removed points per frame;
8. accumulation: the kept points of every frame into the world map (`accumulate.py`).

Frames are read twice (steps 1-5, then 5-7) instead of being held in memory: a long drive costs
per-point flags, not point clouds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.core.errors import ConfigError
from app.core.progress import Progress, Stopwatch
from app.core.sensors import SensorKind
from app.geometry.projection import project
from app.io.sensor_kind import detect_sensor_kind
from app.io.survey import Camera, Frame, Survey
from app.pipelines.clutter.clusters import frame_clusters, object_hosts
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.evidence_store import SpilledEvidence
from app.pipelines.clutter.expansion import (
    ClusterSizes,
    cluster_sizes,
    expand_instances,
    majority_class,
)
from app.pipelines.clutter.freespace import FreeSpaceMap, free_groups, off_ground
from app.pipelines.clutter.fusion import FrameEvidence, fuse
from app.pipelines.clutter.instances import camera_instances, mask_components
from app.pipelines.clutter.masking import mask_points
from app.pipelines.clutter.motion import object_shape
from app.pipelines.clutter.shapes import VehicleShapes, load_vehicle_shapes, shape_inputs
from app.pipelines.clutter.tracking import Observation, Tracker, TrackEvidence

ClassMaps = Callable[[Frame], np.ndarray]  # frame -> (H, W) uint8 clutter class map

FRAME_PERIOD = 0.1  # seconds between frames when the survey has no timestamps (10 Hz)
LOW_BODY = 1.0  # metres above the ground: a person's legs and hips (`Track.walk_speed`)


@dataclass
class ClutterResult:
    frame_ids: list[str]
    removed: list[np.ndarray]  # per frame, (N,) bool in file order
    in_view: list[np.ndarray]  # per frame, (N,) bool: the point projects into the camera image
    evidence: list[FrameEvidence] | SpilledEvidence
    tracks: TrackEvidence | None
    timings: dict[str, float] = field(default_factory=dict)
    # per frame of the result, its index in the survey (a tile runs some of the frames)
    frame_numbers: np.ndarray | None = None

    def frame_labels(self) -> dict[str, np.ndarray]:
        """The contract's labels: per frame, uint8 1 = removed, 0 = kept."""
        return {f: r.astype(np.uint8) for f, r in zip(self.frame_ids, self.removed, strict=True)}


SIGHT_FRAMES = 16  # frames sampled to tell whether the camera ever sees the scanned points


def camera_sees_scans(survey: Survey, camera: Camera) -> bool:
    """Whether the scanner's points fall into the camera's image on any of `SIGHT_FRAMES`
    frames with an image of it, spread over the survey (none with an image: False). A profile
    scanner sweeps a plane beside and behind a forward-looking camera: no mask can apply to its
    points, so the run needs neither the segmentation network nor its weights (a tilted profile
    scanner that scans ahead does)."""
    framed = [f for f in survey.frames if camera.name in f.image_paths]
    step = max(1, len(framed) // SIGHT_FRAMES)
    for frame in framed[::step][:SIGHT_FRAMES]:
        xyz = frame.points().xyz
        if project(xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height).in_image.any():
            return True
    return False


class ClutterPipeline:
    def __init__(
        self,
        config: ClutterConfig | None = None,
        class_maps: ClassMaps | None = None,
        shape_model: VehicleShapes | None = None,
    ):
        self.config = config or ClutterConfig()
        self.class_maps = class_maps
        self.shape_model = shape_model  # instead of the shipped classifier (a benchmark's)
        self.shapes: VehicleShapes | None = None
        # the survey and camera name `camera` last answered for, and its answer (it samples
        # frames: a tile asks before segmenting and `run` asks again)
        self._camera_for: tuple[Survey, str, Camera | None] | None = None

    def vehicle_shapes(self, survey: Survey) -> VehicleShapes | None:
        """The 3D vehicle classifier where clutter mode asks for it and the survey's scanner is
        of the kind it was trained for (rotating); None elsewhere (a profile scanner's frames
        are slices, not objects)."""
        cfg = self.config
        if cfg.mode != "clutter" or not cfg.vehicle_shapes or not cfg.use_tracking:
            return None
        if detect_sensor_kind(survey).kind is not SensorKind.ROTATING:
            return None
        return self.shape_model or load_vehicle_shapes()

    def camera(self, survey: Survey) -> Camera | None:
        """The camera whose images are segmented; None when the survey has none, none of its
        frames has an image of it, its images never show what the scanner scans
        (`camera_sees_scans`), or the camera is off."""
        if not self.config.use_camera or not survey.cameras:
            return None
        name = self.config.camera or next(iter(survey.cameras))
        if name not in survey.cameras:
            known = ", ".join(survey.cameras)
            raise ConfigError("camera", f"survey {survey.name} has no camera {name!r} ({known})")
        cached = self._camera_for
        if cached is None or cached[0] is not survey or cached[1] != name:  # identity, not ==
            camera = survey.cameras[name]
            # calibrated but no image recorded, or images that never show the scans: no masks
            seen = camera_sees_scans(survey, camera)
            self._camera_for = (survey, name, camera if seen else None)
        return self._camera_for[2]

    def run(
        self,
        survey: Survey,
        progress: Progress | None = None,
        only: np.ndarray | None = None,
        spill: Path | None = None,
    ) -> ClutterResult:
        """Every frame of the survey, or the frames whose indices `only` lists (ascending: a
        tile's, `tiled.py`): they are numbered, timed and re-centred as in the whole survey,
        so a frame's evidence does not depend on which frames ran with it. With `spill`, the
        frames' evidence waits in that folder instead of memory (`evidence_store`; the
        caller closes `result.evidence` when done with it)."""
        cfg = self.config
        report = progress or (lambda stage, fraction: None)
        clock = Stopwatch()
        camera = self.camera(survey)
        self.shapes = self.vehicle_shapes(survey)
        if camera is not None and self.class_maps is None:
            raise ConfigError("class_maps", "a camera is in use but no segmenter was given")
        every = list(survey.frames)
        times = _frame_times(every)
        numbers = np.arange(len(every)) if only is None else np.asarray(only, dtype=np.int64)
        frames = [every[int(k)] for k in numbers]
        space = None
        if cfg.use_free_space:
            origin = every[0].pose[:3, 3] if every else None
            space = FreeSpaceMap(
                cfg.dufomap_resolution, cfg.dufomap_d_s, cfg.dufomap_d_p, cfg.threads, origin
            )
        tracker = Tracker(cfg.track_gate) if cfg.use_tracking else None
        evidence: list[FrameEvidence] | SpilledEvidence = (
            [] if spill is None else SpilledEvidence(spill)
        )
        observations: list[Observation] = []
        for i, frame in enumerate(frames):  # steps 1-5 (free space: rays in)
            report("frames", i / max(len(frames), 1))
            with clock("read"):
                xyz = frame.points().xyz
            number = int(numbers[i])
            ev, obs = self._frame(number, times[number], frame, xyz, camera, clock)
            if tracker is not None:
                with clock("tracking"):
                    tracker.step(obs)
            if space is not None:
                with clock("free_space"):
                    space.integrate(xyz, frame.pose)
            evidence.append(ev)
            observations.append(obs)
        if space is not None:  # step 5: which points lie in free space
            for i, frame in enumerate(frames):
                report("free space", i / max(len(frames), 1))
                with clock("read"):
                    xyz = frame.points().xyz
                with clock("free_space"):
                    ev = evidence[i]
                    free = space.flags(xyz, frame.pose)
                    if cfg.free_ground == "near_objects":
                        free = off_ground(free, xyz, ev.ground, cfg.halo_radius)
                    ev.free = free
                    if tracker is not None and cfg.keep_static_tracks:  # fusion's only reader
                        ev.free_group = free_groups(
                            xyz, ev.cluster, free, cfg.min_track_points, cfg.cluster_voxel
                        )
                    evidence[i] = ev
                    observations[i].count_free(ev.cluster, ev.free)
        tracks = None
        if tracker is not None:
            report("tracking", 0.0)
            with clock("tracking"):
                tracks = tracker.evidence(observations, cfg.min_track_frames)
        with clock("fusion"):
            removed = fuse(evidence, tracks, cfg)
        report("done", 1.0)
        return ClutterResult(
            frame_ids=[f.frame_id for f in frames],
            removed=removed,
            in_view=[e.in_view for e in evidence],
            evidence=evidence,
            tracks=tracks,
            timings=clock.rounded(),
            frame_numbers=numbers,
        )

    def _frame(
        self,
        index: int,
        time_s: float,
        frame: Frame,
        xyz: np.ndarray,
        camera: Camera | None,
        clock: Stopwatch,
    ) -> tuple[FrameEvidence, Observation]:
        """Steps 2-4 on one frame: clusters, masks, instances, expansion."""
        cfg = self.config
        with clock("clusters"):
            clusters = frame_clusters(
                xyz, cfg.cluster_voxel, cfg.ground_cell, cfg.ground_tolerance, cfg.max_range
            )
            sizes = cluster_sizes(xyz, clusters)
            object_sized = sizes.within(cfg.max_object_extent, cfg.max_object_height)
        n = len(xyz)
        in_view = np.zeros(n, dtype=bool)
        padded = np.zeros(n, dtype=bool)
        instance = np.full(n, -1, dtype=np.int32)
        mask_class = np.zeros(n, dtype=np.uint8)
        if camera is not None and camera.name in frame.image_paths:
            with clock("segmentation"):
                class_map = self.class_maps(frame)
            with clock("projection_masking"):
                masking = mask_points(xyz, camera, class_map, cfg.mask_padding_px)
            with clock("instances"):
                instance = camera_instances(
                    masking,
                    mask_components(class_map),
                    cfg.depth_gap,
                    cfg.min_instance_points,
                    eligible=clusters.label >= 0,
                )
            in_view, padded, mask_class = masking.in_view, masking.padded, masking.mask_class
        with clock("expansion"):
            if cfg.expansion == "pad":
                camera_removed = padded
                cluster_class = majority_class(clusters.label, mask_class, clusters.count)
            else:
                grown = expand_instances(
                    xyz,
                    clusters,
                    instance,
                    mask_class,
                    in_view,
                    cfg.min_mask_fraction,
                    object_sized,
                    cfg.halo_radius,
                    cfg.min_seed_share,
                    cfg.min_instance_points,
                    sizes if cfg.class_sizes else None,
                )
                camera_removed, cluster_class = grown.removed, grown.cluster_class
        world = xyz @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        observation = _observation(
            index, time_s, world, clusters.label, cluster_class, object_sized,
            cfg.min_track_points, with_shapes=cfg.use_tracking, in_view=in_view, sizes=sizes,
            low=clusters.above_ground <= LOW_BODY,
        )  # fmt: skip
        if self.shapes is not None:
            with clock("shapes"):
                inputs = shape_inputs(
                    xyz, clusters.label, clusters.above_ground, observation.trackable, index
                )
                observation.vehicle = self.shapes.probability(inputs)
        host = None
        if cfg.use_tracking and cfg.attach_pieces:
            with clock("tracking"):
                host = object_hosts(
                    xyz, clusters.label, observation.trackable,
                    clusters.above_ground <= cfg.ground_tolerance, cfg.tyre_radius,
                    cfg.piece_radius, cfg.tyre_angle,
                )  # fmt: skip
        evidence = FrameEvidence(
            host=host,
            cluster_extent=sizes.extent.astype(np.float32),
            cluster_top=sizes.top.astype(np.float32),
            in_view=in_view,
            camera_removed=camera_removed,
            padded=padded,
            cluster=clusters.label,
            free=np.zeros(n, dtype=bool),
            ground=clusters.above_ground <= cfg.ground_tolerance,
            instance=instance,
            mask_class=mask_class,
        )
        return evidence, observation


def _frame_times(frames: list[Frame]) -> np.ndarray:
    stamps = [f.timestamp for f in frames]
    if all(s is not None for s in stamps) and len(set(stamps)) == len(stamps):
        return np.asarray(stamps, dtype=np.float64)
    return np.arange(len(frames)) * FRAME_PERIOD


def _observation(
    frame: int,
    time_s: float,
    world: np.ndarray,
    label: np.ndarray,
    cluster_class: np.ndarray,
    object_sized: np.ndarray,
    min_points: int,
    with_shapes: bool = True,
    in_view: np.ndarray | None = None,
    sizes: ClusterSizes | None = None,
    low: np.ndarray | None = None,
) -> Observation:
    count = len(object_sized)
    inside = label >= 0
    points = np.bincount(label[inside], minlength=count).astype(np.float64)
    centroids = _centroids(world, label, inside, count)
    low_centroids = None
    if low is not None:  # clusters without a lower body keep their centroid
        low_centroids = _centroids(world, label, inside & low, count, centroids)
    trackable = object_sized & (points >= min_points)
    seen = None
    if in_view is not None:
        seen = 2 * np.bincount(label[inside & in_view], minlength=count) > points
    return Observation(
        frame=frame,
        time=float(time_s),
        centroids=centroids,
        points=points,
        camera_class=cluster_class,
        free_points=np.zeros(count),
        trackable=trackable,
        shapes=_cluster_shapes(world, label, trackable) if with_shapes else None,
        seen=seen,
        extent=None if sizes is None else sizes.extent,
        top=None if sizes is None else sizes.top,
        low_centroids=low_centroids,
    )


def _centroids(
    world: np.ndarray,
    label: np.ndarray,
    use: np.ndarray,
    count: int,
    empty: np.ndarray | None = None,
) -> np.ndarray:
    """(count, 3) centroid of each cluster's points where `use`; `empty`'s rows (default 0)
    for clusters without such points."""
    n = np.bincount(label[use], minlength=count).astype(np.float64)
    sums = np.stack(
        [np.bincount(label[use], weights=world[use, k], minlength=count) for k in range(3)], axis=1
    )
    out = sums / np.maximum(n, 1)[:, None]
    if empty is not None:
        out[n == 0] = empty[n == 0]
    return out


def _cluster_shapes(world: np.ndarray, label: np.ndarray, trackable: np.ndarray) -> list:
    """Per cluster, the registration shape of a trackable one (others: empty)."""
    empty = np.zeros((0, 3))
    shapes = [empty] * len(trackable)
    chosen = np.flatnonzero(trackable[np.maximum(label, 0)] & (label >= 0))
    if len(chosen) == 0:
        return shapes
    order = chosen[np.argsort(label[chosen], kind="stable")]
    ids, starts = np.unique(label[order], return_index=True)
    for cluster, part in zip(ids, np.split(order, starts[1:]), strict=True):
        shapes[int(cluster)] = object_shape(world[part], seed=int(cluster))
    return shapes
