"""Fusion by mode: which points of each frame go.

- `dynamic`: objects that moved. A tracked object moved when at least `min_free_fraction` of its
  points lie in observed free space and it stands taller than a curb (`min_track_height`); or
  when the camera classified it and its registered speed reaches `min_speed` (a person: its
  lower body went `min_walk_speed`, `Track.walk_speed`; a walking body is not rigid and
  registering it is noisy); or (`track_motion`) when the camera
  never classified it (outside the view, or missed) and, over `min_motion_frames` frames, its
  registered surface went `min_track_speed` or faster (`Track.surface_speed`: links without a
  registration do not count) in one direction (`min_straightness`), no faster than a vehicle
  drives (`max_track_speed`), standing taller than a curb (`min_track_height`: a rotating
  scanner's ground rings sweep along with it). The centroid of an unclassified cluster drifts
  with the viewpoint (a fence whose visible part slides along with the vehicle "moves" at
  walking pace), so the bar for objects nobody named is a car's speed, not a walker's. A moving
  track goes in every frame, inside and outside the camera view. Free-space points outside any
  tracked object (DUFOMap's own decision) go too; with `keep_static_tracks`, not those of an
  object followed over `min_motion_frames` that did not move by any evidence and has fewer than
  `max_static_free` of its points free (grazing rays flag a few points of a parked van free; a
  car creeping in a queue has more), except free points that form a person-sized group
  (`freespace.free_groups`: someone walking past, merged into its cluster).
- Both modes: an object's loose pieces and tyres (`attach_pieces`) go where most of its points go.
- `clutter` (the paper's definition, for HD maps): every movable object, parked ones included:
  the camera's expanded instances, every frame of a track the camera ever classified (after the
  object left the view; in the view when the camera classed it in at least `min_class_share` of
  the frames where it saw it), every frame of a track whose clusters are vehicle-shaped in 3D
  (`vehicle_shapes`: a car in deep shadow, a trailer, a site machine the camera cannot name),
  and everything the dynamic mode removes. With `outvote_masks`
  the vote also goes the other way: a track the camera saw in some frames but classed in fewer
  than `min_class_share` of them is background a mask grazed now and then (a kiosk, an awning,
  a column beside a car): only the points on its camera instances go, not its whole cluster,
  and its class is not carried anywhere.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.expansion import PERSON, fits_class
from app.pipelines.clutter.tracking import TrackEvidence


@dataclass
class FrameEvidence:
    """Per point of one frame: what each source says."""

    in_view: np.ndarray  # (N,) bool
    camera_removed: np.ndarray  # (N,) bool: camera instance after expansion (or padded mask)
    padded: np.ndarray  # (N,) bool: under a padded mask
    cluster: np.ndarray  # (N,) int32 cluster id, -1 = ground / out of range
    free: np.ndarray  # (N,) bool: DUFOMap free-space flag
    ground: np.ndarray | None = None  # (N,) bool: within ground_tolerance of the frame's ground
    # which camera instance a point lies on (review; fusion keeps only these of outvoted tracks)
    instance: np.ndarray | None = None  # (N,) int32 camera instance id, -1 = none
    mask_class: np.ndarray | None = None  # (N,) uint8 clutter class under the unpadded mask
    # the trackable cluster a loose point belongs to (`clusters.object_hosts`), -1 = none
    host: np.ndarray | None = None  # (N,) int32
    # per cluster: the longer side of its horizontal box and its top above the ground, metres
    cluster_extent: np.ndarray | None = None  # (C,) float32
    cluster_top: np.ndarray | None = None  # (C,) float32
    # free points in a person-sized group (`freespace.free_groups`)
    free_group: np.ndarray | None = None  # (N,) bool


def outvoted(tracks: TrackEvidence, config: ClutterConfig) -> np.ndarray:
    """(T,) bool: clutter mode, the camera classed the track in a minority of the frames that
    saw it."""
    if config.mode != "clutter" or not config.outvote_masks:
        return np.zeros(len(tracks.class_share), dtype=bool)
    return (tracks.seen_frames > 0) & (tracks.class_share < config.min_class_share)


def vehicle_shaped(tracks: TrackEvidence, config: ClutterConfig) -> np.ndarray:
    """(T,) bool: clutter mode, a track followed over `min_track_frames` whose clusters are
    vehicle-shaped in 3D (`shapes.py`), whatever the camera says."""
    if config.mode != "clutter" or not config.vehicle_shapes or tracks.vehicle_shape is None:
        return np.zeros(len(tracks.tracks), dtype=bool)
    return (tracks.vehicle_shape >= config.min_vehicle_shape) & (
        tracks.frame_counts >= config.min_track_frames
    )


def track_decisions(tracks: TrackEvidence, config: ClutterConfig) -> tuple[np.ndarray, np.ndarray]:
    """(moving, movable) per track."""
    shaped = vehicle_shaped(tracks, config)
    movable = ((tracks.camera_class > 0) & ~outvoted(tracks, config)) | shaped
    walker = movable & (tracks.camera_class == PERSON)
    moving = movable & ~walker & (tracks.speed >= config.min_speed)
    classed = movable & ~shaped  # the camera named it (the shape rule is clutter mode's)
    if config.walk_measure == "lower_body" and tracks.walk_speed is not None:
        moving |= walker & (tracks.walk_speed >= config.min_walk_speed)
    else:
        moving |= walker & (tracks.speed >= config.min_speed)
    if config.track_motion and tracks.straightness is not None:
        moving |= (
            ~classed
            & (tracks.frame_counts >= config.min_motion_frames)
            & (tracks.surface_speed >= config.min_track_speed)
            & (tracks.surface_speed <= config.max_track_speed)
            & (tracks.straightness >= config.min_straightness)
            & (tracks.top >= config.min_track_height)
        )
    if config.use_free_space:
        # a curb or road patch followed over the frames is not an object that moved, however
        # many of its points DUFOMap flags (rays graze it); its free points still go one by one
        tall = True if tracks.top is None else tracks.top >= config.min_track_height
        moving |= (tracks.free_fraction >= config.min_free_fraction) & tall
    return moving, movable


def _out_of_view_clusters(ev: FrameEvidence, count: int) -> np.ndarray:
    """(count,) bool: fewer than half of the cluster's points are seen by the camera."""
    clustered = ev.cluster >= 0
    size = np.bincount(ev.cluster[clustered], minlength=count)
    seen = np.bincount(ev.cluster[clustered & ev.in_view], minlength=count)
    return 2 * seen < size


def fuse(
    evidence: Sequence[FrameEvidence], tracks: TrackEvidence | None, config: ClutterConfig
) -> list[np.ndarray]:
    """Per frame, (N,) bool removed."""
    if tracks is not None:
        moving, movable = track_decisions(tracks, config)
        shaped = vehicle_shaped(tracks, config)
        background = outvoted(tracks, config) & ~shaped
        settled = (
            ~moving
            & (tracks.frame_counts >= config.min_motion_frames)
            & (tracks.free_fraction < config.max_static_free)
        )
    removed = []
    for i, ev in enumerate(evidence):
        gone = np.zeros(len(ev.free), dtype=bool)
        if config.use_free_space:
            # in the view the camera vouches for objects: a free-space point it sees as background
            # (no padded mask on it) is DUFOMap's noise at surfaces grazed by rays
            gone |= ev.free & (~ev.in_view | ev.padded | (config.free_in_view == "all"))
        if tracks is not None:
            point_track = np.full(len(ev.cluster), -1, dtype=np.int64)
            clustered = ev.cluster >= 0
            point_track[clustered] = tracks.cluster_track[i][ev.cluster[clustered]]
            tracked = point_track >= 0
            if config.keep_static_tracks:  # followed over the frames and it did not move
                still = np.zeros(len(gone), dtype=bool)
                still[tracked] = settled[point_track[tracked]]
                if ev.free_group is not None:  # ... unless someone walked past it
                    still &= ~ev.free_group
                gone &= ~still
        if config.mode == "clutter" and config.use_camera:
            camera = ev.camera_removed
            if tracks is not None and ev.instance is not None and background.any():
                voted = np.zeros(len(camera), dtype=bool)
                voted[tracked] = background[point_track[tracked]]
                camera = camera & ~(voted & (ev.instance < 0))
            gone |= camera
        if tracks is not None:
            # a classified track's decision reaches only clusters its class can be (a person's
            # track that merged into the stall it stood at does not take the stall)
            track_ids = tracks.cluster_track[i]
            fits = np.ones(len(track_ids), dtype=bool)
            if config.class_sizes and ev.cluster_extent is not None and ev.cluster_top is not None:
                klass = np.where(track_ids >= 0, tracks.camera_class[track_ids], 0)
                fits = fits_class(ev.cluster_extent, ev.cluster_top, klass)
            point_fits = np.zeros(len(gone), dtype=bool)
            point_fits[clustered] = fits[ev.cluster[clustered]]
            tracked_fit = tracked & point_fits
            gone[tracked_fit] |= moving[point_track[tracked_fit]]
            if config.mode == "clutter":
                # a classified object keeps its class where the camera cannot see it; in the view
                # too when the camera classed it in most frames where it saw it (a missed mask)
                hidden = _out_of_view_clusters(ev, len(track_ids))
                carry = np.zeros(len(track_ids), dtype=bool)
                linked = (track_ids >= 0) & fits
                held = tracks.class_share[track_ids[linked]] >= config.min_class_share
                held |= shaped[track_ids[linked]]  # a vehicle whatever the camera says
                carry[linked] = movable[track_ids[linked]] & (hidden[linked] | held)
                gone[clustered] |= carry[ev.cluster[clustered]]
        if ev.host is not None:
            gone |= _with_their_hosts(gone, ev)
        removed.append(gone)
    return removed


def _with_their_hosts(gone: np.ndarray, ev: FrameEvidence) -> np.ndarray:
    """(N,) bool: the loose pieces and tyres (`FrameEvidence.host`) of objects whose points
    mostly go, whatever took them (motion, a mask, a carried class): a parked car's wheels
    within the ground's tolerance are as much car as its doors."""
    hosted = np.flatnonzero(ev.host >= 0)
    if not len(hosted):
        return np.zeros(len(gone), dtype=bool)
    clustered = ev.cluster >= 0
    count = int(max(ev.cluster.max(initial=-1), ev.host.max(initial=-1))) + 1
    size = np.bincount(ev.cluster[clustered], minlength=count)
    taken = np.bincount(ev.cluster[clustered & gone], minlength=count)
    out = np.zeros(len(gone), dtype=bool)
    out[hosted] = 2 * taken[ev.host[hosted]] > size[ev.host[hosted]]
    return out
