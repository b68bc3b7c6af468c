"""Free-space evidence: DUFOMap (Duberg et al. 2024) integrates every frame's rays with its pose;
a point that lies in space some other ray saw through is dynamic.

DUFOMap works in float32: frames are re-centred on the first pose before they go in, so
georeferenced coordinates keep their millimetres.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from app.core.errors import DependencyMissingError
from app.pipelines.clutter.clusters import voxel_components
from app.pipelines.clutter.expansion import CLASS_EXTENT, PERSON


def _dufomap_class():
    os.environ.setdefault("GLOG_minloglevel", "2")  # DUFOMap logs its config on every map
    try:
        from dufomap import dufomap
    except ImportError as exc:  # pragma: no cover - it is a pinned dependency
        raise DependencyMissingError(
            "dufomap is not installed (pip install dufomap==1.1.1): free-space evidence needs it"
        ) from exc
    return dufomap


class FreeSpaceMap:
    """DUFOMap fed frame by frame (`integrate`), then asked per frame which points lie in free
    space (`flags`), so a long drive never has to sit in memory at once."""

    def __init__(
        self,
        resolution: float = 0.1,
        d_s: float = 0.2,
        d_p: int = 1,
        threads: int = 0,
        origin: np.ndarray | None = None,
    ) -> None:
        """`origin`: the world point frames are re-centred on (default: the first frame's
        sensor); the tiles of one survey share it, so their voxels are the same voxels."""
        self._engine = _dufomap_class()(resolution, d_s, d_p, num_threads=threads)
        self._origin = None if origin is None else np.array(origin, dtype=np.float64)[:3]
        self._propagated = False

    def _local(self, pose: np.ndarray) -> np.ndarray:
        local = np.array(pose, dtype=np.float64)
        if self._origin is None:
            self._origin = local[:3, 3].copy()
        local[:3, 3] -= self._origin
        return local

    def integrate(self, xyz: np.ndarray, pose: np.ndarray) -> None:
        """Add one frame's rays: sensor-frame points `xyz`, 4x4 sensor -> world `pose`."""
        if self._propagated:
            raise RuntimeError("FreeSpaceMap: all frames must be integrated before flags()")
        self._engine.run(np.asarray(xyz, dtype=np.float32), self._local(pose), True)

    def flags(self, xyz: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """(N,) bool: the frame's point lies in space that some ray passed through."""
        if not self._propagated:
            self._engine.oncePropagateCluster(if_propagate=True, if_cluster=False)
            self._propagated = True
        local = self._local(pose)
        world = np.asarray(xyz, dtype=np.float64) @ local[:3, :3].T + local[:3, 3]
        if len(world) == 0:
            return np.zeros(0, dtype=bool)
        return np.asarray(self._engine.segment(world.astype(np.float32), local, False)) > 0


def free_space_flags(
    frames_xyz: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    resolution: float = 0.1,
    d_s: float = 0.2,
    d_p: int = 1,
    threads: int = 0,
) -> list[np.ndarray]:
    """Per frame, (N,) bool free-space flags of in-memory frames (DUFOMap alone, the baseline)."""
    space = FreeSpaceMap(resolution, d_s, d_p, threads)
    for xyz, pose in zip(frames_xyz, poses, strict=True):
        space.integrate(xyz, pose)
    return [space.flags(xyz, pose) for xyz, pose in zip(frames_xyz, poses, strict=True)]


def off_ground(free: np.ndarray, xyz: np.ndarray, ground: np.ndarray, radius: float) -> np.ndarray:
    """Free-space flags without the ground's grazing-ray noise.

    Rays meet the road at a grazing angle, so DUFOMap calls road points free a few decimetres
    in front of where another scan's ray hit the road: thousands of road points per frame on
    SemanticKITTI 04. A ground-level point stays free only when a free point above the ground
    lies within `radius` of it: the feet and wheels of a moving object.
    """
    flagged = free & ground
    lifted = free & ~ground
    kept = free & ~ground
    if flagged.any() and lifted.any() and radius > 0:
        distance, _ = cKDTree(xyz[lifted]).query(
            xyz[flagged], k=1, distance_upper_bound=radius, workers=-1
        )
        kept[np.flatnonzero(flagged)[np.isfinite(distance)]] = True
    return kept


def free_groups(
    xyz: np.ndarray, cluster: np.ndarray, free: np.ndarray, min_points: int, voxel: float
) -> np.ndarray:
    """(N,) bool: free points of tracked clusters that form a person-sized group, at least
    `min_points` connected at `voxel`. DUFOMap's grazing rays flag thin bands along a parked
    car's surface; a person walking past it, merged into its cluster, is a compact group."""
    out = np.zeros(len(xyz), dtype=bool)
    at = np.flatnonzero((cluster >= 0) & free)
    if len(at) < min_points:
        return out
    group = voxel_components(xyz[at], voxel)
    count = int(group.max()) + 1
    lo = np.full((count, 2), np.inf)
    hi = np.full((count, 2), -np.inf)
    np.minimum.at(lo, group, xyz[at, :2])
    np.maximum.at(hi, group, xyz[at, :2])
    many = np.bincount(group, minlength=count) >= min_points
    compact = many & (np.max(hi - lo, axis=1) <= CLASS_EXTENT[PERSON])
    out[at] = compact[group]
    return out
