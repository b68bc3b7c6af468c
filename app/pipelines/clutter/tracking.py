"""Tracking: object-sized clusters linked across frames in world coordinates.

An object seen by the camera keeps its class after it leaves the view, and an object that moved
anywhere is moving in every frame. Each frame's clusters are matched to the tracks' predicted
positions (constant velocity) by the Hungarian method, gated at `gate` metres (twice that for
tracks without a velocity yet). A track's position advances at each link by the registered
displacement of its surface (`motion.py`); where a frame gave no surface (a test, an empty
shape) or the surfaces do not overlap, the centroid step stands in. Its speed is the median
speed over its links; it needs `min_frames` observations.

Tracking streams: `Tracker.step` takes each frame's observation as the frame is read and frees
its shapes, so a long drive holds one shape per active track, not per frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.optimize import linear_sum_assignment

from app.pipelines.clutter.expansion import PERSON, fits_class
from app.pipelines.clutter.motion import register_many

WALK_WINDOW = 5  # frames over which a person's lower body is followed (half a stride at 10 Hz)


@dataclass
class Observation:
    """One frame's clusters: world centroids and their evidence."""

    frame: int
    time: float
    centroids: np.ndarray  # (C, 3) world, float64
    points: np.ndarray  # (C,) point count
    camera_class: np.ndarray  # (C,) uint8, 0 = no camera instance
    free_points: np.ndarray  # (C,) points in observed free space
    trackable: np.ndarray  # (C,) bool: object-sized
    seen: np.ndarray | None = None  # (C,) bool: the camera sees most of the cluster
    extent: np.ndarray | None = None  # (C,) metres: the longer side of its horizontal box
    top: np.ndarray | None = None  # (C,) metres above the ground
    # (C, 3) world centroid of the cluster's lower body (`LOW_BODY`: legs and hips of a
    # person, whose swinging arms and turning torso make registration noisy); None: centroids
    low_centroids: np.ndarray | None = None
    vehicle: np.ndarray | None = None  # (C,) P(vehicle) by 3D shape (`shapes.py`); None: unknown
    # per cluster, its downsampled world points (`motion.object_shape`); None = centroids only
    shapes: list[np.ndarray] | None = None

    def low(self, cluster: int) -> np.ndarray | None:
        return None if self.low_centroids is None else self.low_centroids[cluster]

    def person_sized(self, cluster: int) -> bool:
        """The cluster can be one person (True when its size was not measured)."""
        if self.extent is None or self.top is None:
            return True
        return bool(fits_class(self.extent[cluster], self.top[cluster], PERSON))

    def count_free(self, label: np.ndarray, free: np.ndarray) -> None:
        """Set `free_points` from the frame's per-point cluster labels and free-space flags."""
        inside = label >= 0
        self.free_points = np.bincount(
            label[inside], weights=free[inside], minlength=len(self.points)
        )


@dataclass
class Track:
    frames: list[int] = field(default_factory=list)
    clusters: list[int] = field(default_factory=list)
    times: list[float] = field(default_factory=list)
    centroids: list[np.ndarray] = field(default_factory=list)
    positions: list[np.ndarray] = field(default_factory=list)  # registered, from the first
    velocity: np.ndarray | None = None
    shape: np.ndarray | None = None  # the last observation's points
    lows: list[np.ndarray] = field(default_factory=list)  # lower-body centroids
    registered: list[bool] = field(default_factory=list)  # per link: surfaces registered
    person_sized: list[bool] = field(default_factory=list)  # per observation

    def predict(self, time: float) -> np.ndarray:
        if self.velocity is None:
            return self.centroids[-1]
        return self.centroids[-1] + self.velocity * (time - self.times[-1])

    def add(
        self,
        frame: int,
        cluster: int,
        time: float,
        centroid: np.ndarray,
        shape: np.ndarray | None = None,
        moved: np.ndarray | None = None,
        low: np.ndarray | None = None,
        person_sized: bool = True,
    ) -> None:
        """Link an observation; `moved` is its registered displacement (None: centroid step),
        `low` its lower-body centroid (None: the centroid)."""
        if not self.centroids:
            self.positions.append(np.zeros(3))
        else:
            centroid_step = centroid - self.centroids[-1]
            if time > self.times[-1]:
                step = centroid_step / (time - self.times[-1])
                self.velocity = step if self.velocity is None else 0.5 * (self.velocity + step)
            self.positions.append(self.positions[-1] + (centroid_step if moved is None else moved))
            self.registered.append(moved is not None)
        self.frames.append(frame)
        self.clusters.append(cluster)
        self.times.append(time)
        self.centroids.append(centroid)
        self.lows.append(centroid if low is None else low)
        self.person_sized.append(person_sized)
        self.shape = shape

    def speed(self, min_frames: int) -> float:
        """m/s: the median over the track's links of horizontal distance moved per second.

        A median, not a line fit: one wrong link (the track jumping to a neighbouring cluster,
        two surfaces with no overlap) must not make a parked car move. 0 for short tracks.
        """
        if len(self.times) < min_frames:
            return 0.0
        dt = np.diff(np.asarray(self.times))
        moved = np.linalg.norm(np.diff(np.asarray(self.positions)[:, :2], axis=0), axis=1)
        timed = dt > 0
        if not timed.any():
            return 0.0
        return float(np.median(moved[timed] / dt[timed]))

    def surface_speed(self, min_frames: int) -> float:
        """m/s: `speed` over the links whose surfaces were registered only (a centroid step
        is the viewpoint's slide as much as the object's motion); 0 with fewer than
        `min_frames` - 1 such links."""
        if sum(self.registered) < max(min_frames - 1, 1):
            return 0.0
        dt = np.diff(np.asarray(self.times))
        moved = np.linalg.norm(np.diff(np.asarray(self.positions)[:, :2], axis=0), axis=1)
        use = np.asarray(self.registered) & (dt > 0)
        return float(np.median(moved[use] / dt[use])) if use.any() else 0.0

    def walk_speed(self, min_frames: int) -> float:
        """m/s: the median over the track of how far its lower-body centroid went in
        `WALK_WINDOW` frames, per second. A person's measure: legs and hips move with the
        person whatever the arms do, a window of half a stride averages a step's sway, and the
        median outlasts a link to a passer-by. Windows that start or end on a cluster larger
        than a person (merged with a stall it stood at: the stall's lower part slides with the
        viewpoint) do not count. 0 for short tracks."""
        if len(self.times) < max(min_frames, 2):
            return 0.0
        window = min(WALK_WINDOW, len(self.times) - 1)
        lows = np.asarray(self.lows)[:, :2]
        times = np.asarray(self.times)
        small = np.asarray(self.person_sized, dtype=bool)
        went = np.linalg.norm(lows[window:] - lows[:-window], axis=1)
        took = times[window:] - times[:-window]
        timed = (took > 0) & small[window:] & small[:-window]
        return float(np.median(went[timed] / took[timed])) if timed.any() else 0.0

    def straightness(self) -> float:
        """0..1: how far the track's surface got over the way it went (1: one direction all
        along, as a driving car; near 0: back and forth, as registration noise on a parked
        car or a hedge)."""
        if len(self.positions) < 2:
            return 0.0
        steps = np.diff(np.asarray(self.positions)[:, :2], axis=0)
        travelled = float(np.linalg.norm(steps, axis=1).sum())
        return float(np.linalg.norm(steps.sum(axis=0)) / travelled) if travelled > 0 else 0.0


@dataclass
class TrackEvidence:
    """Per track: speed, camera class, share of points in free space; per cluster: its track."""

    tracks: list[Track]
    speed: np.ndarray  # (T,) m/s
    camera_class: np.ndarray  # (T,) uint8 most frequent class of its camera instances
    free_fraction: np.ndarray  # (T,)
    class_share: np.ndarray  # (T,) of the frames whose camera saw the object, those that classed it
    seen_frames: np.ndarray  # (T,) frames whose camera saw most of the object
    cluster_track: list[np.ndarray]  # per frame, (C,) int32 track id, -1 = untracked
    # (T,) the highest top of its clusters over the frames, metres (inf where not measured)
    top: np.ndarray | None = None
    straightness: np.ndarray | None = None  # (T,) `Track.straightness`
    walk_speed: np.ndarray | None = None  # (T,) m/s, `Track.walk_speed`
    surface_speed: np.ndarray | None = None  # (T,) m/s, `Track.surface_speed`
    # (T,) P(vehicle) by 3D shape over its frames, weighed by their points
    vehicle_shape: np.ndarray | None = None

    @cached_property
    def frame_counts(self) -> np.ndarray:
        """(T,) observations per track (fusion asks for it three times per run)."""
        return np.array([len(t.frames) for t in self.tracks], dtype=np.int64)


class Tracker:
    """Links each frame's trackable clusters to the tracks as the frames come."""

    def __init__(self, gate: float, max_missed: int = 2):
        self.gate = gate
        self.max_missed = max_missed
        self.tracks: list[Track] = []
        self.active: list[int] = []
        self.cluster_track: list[np.ndarray] = []

    def step(self, obs: Observation) -> None:
        tracks = self.tracks
        shapes = obs.shapes
        ids = np.full(len(obs.centroids), -1, dtype=np.int32)
        candidates = np.flatnonzero(obs.trackable)
        still = [t for t in self.active if obs.frame - tracks[t].frames[-1] <= self.max_missed + 1]
        matched_clusters: set[int] = set()
        if still and len(candidates):
            predicted = np.stack([tracks[t].predict(obs.time) for t in still])
            limit = np.array(
                [self.gate if tracks[t].velocity is not None else 2 * self.gate for t in still]
            )
            cost = np.linalg.norm(predicted[:, None, :] - obs.centroids[candidates][None], axis=2)
            big = 1e6
            cost = np.where(cost <= limit[:, None], cost, big)
            rows, cols = linear_sum_assignment(cost)
            links = [
                (still[r], int(candidates[c]))
                for r, c in zip(rows, cols, strict=True)
                if cost[r, c] < big
            ]
            moved = self._registered(links, obs)
            for (track, cluster), displacement in zip(links, moved, strict=True):
                shape = None if shapes is None else shapes[cluster]
                centroid = obs.centroids[cluster]
                tracks[track].add(obs.frame, cluster, obs.time, centroid, shape, displacement,
                                  obs.low(cluster), obs.person_sized(cluster))  # fmt: skip
                ids[cluster] = track
                matched_clusters.add(cluster)
        for cluster in candidates:
            if int(cluster) in matched_clusters:
                continue
            track = Track()
            shape = None if shapes is None else shapes[cluster]
            track.add(obs.frame, int(cluster), obs.time, obs.centroids[cluster], shape,
                      low=obs.low(cluster), person_sized=obs.person_sized(cluster))  # fmt: skip
            ids[cluster] = len(tracks)
            still.append(len(tracks))
            tracks.append(track)
        for t in set(self.active) - set(still):
            tracks[t].shape = None  # ended: its surface is not needed any more
        self.active = still
        self.cluster_track.append(ids)
        obs.shapes = None

    def _registered(
        self, links: list[tuple[int, int]], obs: Observation
    ) -> list[np.ndarray | None]:
        """Per link, the registered displacement of the track's surface (None: no fit)."""
        moved: list[np.ndarray | None] = [None] * len(links)
        if obs.shapes is None:
            return moved
        both = [
            i
            for i, (track, cluster) in enumerate(links)
            if self.tracks[track].shape is not None
            and len(self.tracks[track].shape)
            and len(obs.shapes[cluster])
        ]
        if not both:
            return moved
        previous = [self.tracks[links[i][0]].shape for i in both]
        current = [obs.shapes[links[i][1]] for i in both]
        predicted = np.stack(
            [obs.centroids[links[i][1]] - self.tracks[links[i][0]].centroids[-1] for i in both]
        )
        fit = register_many(previous, current, predicted)
        for k, i in enumerate(both):
            if np.isfinite(fit.residual[k]):
                moved[i] = fit.displacement[k]
        return moved

    def evidence(self, observations: list[Observation], min_frames: int) -> TrackEvidence:
        """Per-track evidence once every frame was stepped and its free points counted."""
        for track in self.tracks:
            track.shape = None
        return _evidence(self.tracks, observations, self.cluster_track, min_frames)


def track_clusters(
    observations: list[Observation], gate: float, min_frames: int, max_missed: int = 2
) -> TrackEvidence:
    tracker = Tracker(gate, max_missed)
    for obs in observations:
        tracker.step(obs)
    return tracker.evidence(observations, min_frames)


def _evidence(
    tracks: list[Track],
    observations: list[Observation],
    cluster_track: list[np.ndarray],
    min_frames: int,
) -> TrackEvidence:
    n = len(tracks)
    speed = np.array([t.speed(min_frames) for t in tracks]) if n else np.zeros(0)
    votes = np.zeros((n, 256), dtype=np.int64)
    points = np.zeros(n)
    free = np.zeros(n)
    seen = np.zeros(n)
    classed = np.zeros(n)
    top = np.zeros(n)
    shape_sum = np.zeros(n)
    shape_seen = np.zeros(n)
    for obs, ids in zip(observations, cluster_track, strict=True):
        tracked = ids >= 0
        if obs.vehicle is not None:
            # weighed by points: the frames that see most of the object say most about it
            np.add.at(shape_sum, ids[tracked], obs.vehicle[tracked] * obs.points[tracked])
            np.add.at(shape_seen, ids[tracked], obs.points[tracked])
        np.maximum.at(top, ids[tracked], np.inf if obs.top is None else obs.top[tracked])
        np.add.at(votes, (ids[tracked], obs.camera_class[tracked]), 1)
        np.add.at(points, ids[tracked], obs.points[tracked])
        np.add.at(free, ids[tracked], obs.free_points[tracked])
        if obs.seen is not None:
            looked = tracked & obs.seen
            np.add.at(seen, ids[looked], 1)
            np.add.at(classed, ids[looked & (obs.camera_class > 0)], 1)
    votes[:, 0] = 0
    camera_class = np.where(votes.max(axis=1) > 0, votes.argmax(axis=1), 0).astype(np.uint8)
    with np.errstate(invalid="ignore", divide="ignore"):
        free_fraction = np.where(points > 0, free / points, 0.0)
        class_share = np.where(seen > 0, classed / seen, 0.0)
    straightness = np.array([t.straightness() for t in tracks]) if n else np.zeros(0)
    walk = np.array([t.walk_speed(min_frames) for t in tracks]) if n else np.zeros(0)
    surface = np.array([t.surface_speed(min_frames) for t in tracks]) if n else np.zeros(0)
    vehicle = shape_sum / np.maximum(shape_seen, 1.0) if shape_seen.any() else None
    return TrackEvidence(
        tracks, speed, camera_class, free_fraction, class_share, seen, cluster_track,
        top, straightness, walk, surface, vehicle,
    )  # fmt: skip
