"""Tracking: object-sized clusters linked across frames in world coordinates.

An object seen by the camera keeps its class after it leaves the view, and an object that moved
anywhere is moving in every frame. Each frame's clusters are matched to the tracks' predicted
positions (constant velocity) by the Hungarian method, gated at `gate` metres (twice that for
tracks without a velocity yet). A track's speed is the least-squares slope of its centroids
over time; it needs `min_frames` observations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment


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
    velocity: np.ndarray | None = None

    def predict(self, time: float) -> np.ndarray:
        if self.velocity is None:
            return self.centroids[-1]
        return self.centroids[-1] + self.velocity * (time - self.times[-1])

    def add(self, frame: int, cluster: int, time: float, centroid: np.ndarray) -> None:
        if self.centroids and time > self.times[-1]:
            step = (centroid - self.centroids[-1]) / (time - self.times[-1])
            self.velocity = step if self.velocity is None else 0.5 * (self.velocity + step)
        self.frames.append(frame)
        self.clusters.append(cluster)
        self.times.append(time)
        self.centroids.append(centroid)

    def speed(self, min_frames: int) -> float:
        """m/s from a straight-line fit of the horizontal centroids; 0 for short tracks."""
        if len(self.times) < min_frames:
            return 0.0
        t = np.asarray(self.times) - self.times[0]
        c = np.asarray(self.centroids)[:, :2]
        if np.ptp(t) <= 0:
            return 0.0
        slope = np.polyfit(t, c, 1)[0]
        return float(np.hypot(*slope))


@dataclass
class TrackEvidence:
    """Per track: speed, camera class, share of points in free space; per cluster: its track."""

    tracks: list[Track]
    speed: np.ndarray  # (T,) m/s
    camera_class: np.ndarray  # (T,) uint8 most frequent class of its camera instances
    free_fraction: np.ndarray  # (T,)
    cluster_track: list[np.ndarray]  # per frame, (C,) int32 track id, -1 = untracked


def track_clusters(
    observations: list[Observation], gate: float, min_frames: int, max_missed: int = 2
) -> TrackEvidence:
    tracks: list[Track] = []
    active: list[int] = []
    cluster_track = []
    for obs in observations:
        ids = np.full(len(obs.centroids), -1, dtype=np.int32)
        candidates = np.flatnonzero(obs.trackable)
        still = [t for t in active if obs.frame - tracks[t].frames[-1] <= max_missed + 1]
        matched_clusters: set[int] = set()
        if still and len(candidates):
            predicted = np.stack([tracks[t].predict(obs.time) for t in still])
            limit = np.array([gate if tracks[t].velocity is not None else 2 * gate for t in still])
            cost = np.linalg.norm(predicted[:, None, :] - obs.centroids[candidates][None], axis=2)
            big = 1e6
            cost = np.where(cost <= limit[:, None], cost, big)
            rows, cols = linear_sum_assignment(cost)
            for r, c in zip(rows, cols, strict=True):
                if cost[r, c] >= big:
                    continue
                cluster = int(candidates[c])
                tracks[still[r]].add(obs.frame, cluster, obs.time, obs.centroids[cluster])
                ids[cluster] = still[r]
                matched_clusters.add(cluster)
        for cluster in candidates:
            if int(cluster) in matched_clusters:
                continue
            track = Track()
            track.add(obs.frame, int(cluster), obs.time, obs.centroids[cluster])
            ids[cluster] = len(tracks)
            still.append(len(tracks))
            tracks.append(track)
        active = still
        cluster_track.append(ids)
    return _evidence(tracks, observations, cluster_track, min_frames)


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
    for obs, ids in zip(observations, cluster_track, strict=True):
        tracked = ids >= 0
        np.add.at(votes, (ids[tracked], obs.camera_class[tracked]), 1)
        np.add.at(points, ids[tracked], obs.points[tracked])
        np.add.at(free, ids[tracked], obs.free_points[tracked])
    votes[:, 0] = 0
    camera_class = np.where(votes.max(axis=1) > 0, votes.argmax(axis=1), 0).astype(np.uint8)
    with np.errstate(invalid="ignore", divide="ignore"):
        free_fraction = np.where(points > 0, free / points, 0.0)
    return TrackEvidence(tracks, speed, camera_class, free_fraction, cluster_track)
