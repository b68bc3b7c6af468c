"""Road removal (paper 3.1, first step): drop the road surface and everything far from the road.

The paper removes a point when its z is at or below the road height estimated from the MMS
trajectory and its normal (from neighbouring points) is close to the z axis, and also removes
points far from the road. Here:

- **Road height per station.** The road lies about one mount height below the sensor, but the
  mount height is not assumed: per `station_bin` of arc length the `road_percentile` of z of the
  points within `corridor` metres of the trajectory (laterally) is the road height there (traffic
  and parked cars only add points above it). Bins without such points take the sensor height
  minus the median sensor-to-road offset of the other bins (the measured mount height), or
  `mount_height` when no bin has any.
- **Road points**: z <= road height + `road_tolerance` and normal within `normal_angle_deg` of
  the z axis. Normals: smallest-eigenvalue eigenvector of the covariance of the `normal_k`
  nearest neighbours (cKDTree, batched `eigh`), computed for the candidate points only.
- **Other ground (beyond the paper, `ground_tolerance`)**: horizontal points within that height
  of the local ground (`app.geometry.ground.estimate_ground`) go too. Sidewalks sit a curb height
  above the road; left in, they join every roadside object (guardrail posts, trees, poles,
  walls) into one connected component whose slices crop to whole street sections.
- **Far points**: farther than `road_margin` beyond the road edge on their side (the outermost
  road point per side within `edge_window` metres of station), and never farther than
  `max_lateral` from the trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from app.geometry.ground import estimate_ground
from app.geometry.trajectory import StationIndex, arc_length

EDGE_WINDOW = 5.0  # metres of station each way over which the road edge is the outermost
STATION_BIN = 1.0  # metres of station per road height (a 3-bin median smooths them)


def as_positions(trajectory: np.ndarray) -> np.ndarray:
    """(M, 3) float64 positions from (M, 3) positions or (M, 4, 4) sensor poses."""
    trajectory = np.asarray(trajectory, dtype=np.float64)
    if trajectory.ndim == 3 and trajectory.shape[1:] == (4, 4):
        return trajectory[:, :3, 3]
    return trajectory.reshape(-1, 3)


def trajectory_height(positions: np.ndarray, stations: np.ndarray) -> np.ndarray:
    """Sensor height (z of the trajectory) at the given stations (clamped at both ends)."""
    return np.interp(stations, arc_length(positions), positions[:, 2])


def point_normals(
    xyz: np.ndarray,
    query: np.ndarray | None = None,
    k: int = 10,
    voxel: float | None = 0.1,
    chunk: int = 200_000,
    origin: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (Q, 3) and their reliability (Q,) bool at the `query` indices of `xyz`.

    Local PCA: the smallest-eigenvalue eigenvector of the covariance of the k nearest neighbours;
    sign z >= 0. The neighbours are searched among `voxel`-sized voxel centroids, not raw points:
    a profile scanner puts points ~1 cm apart along a scan line but ~10 cm between lines, so the k
    nearest raw points are all on one line and their covariance has no normal. A normal counts as
    reliable when the neighbourhood is a surface, not a line (second eigenvalue >= 4 x smallest
    and >= 1 % of the largest).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    query = np.arange(len(xyz)) if query is None else np.asarray(query, dtype=np.int64)
    normals = np.zeros((len(query), 3))
    reliable = np.zeros(len(query), dtype=bool)
    if len(query) == 0 or len(xyz) == 0:
        return normals, reliable
    origin = xyz[query].mean(axis=0) if origin is None else np.asarray(origin, np.float64)
    if voxel:
        ijk = np.floor((xyz - origin) / voxel).astype(np.int64)
        ijk -= ijk.min(axis=0)
        keys = np.ravel_multi_index(tuple(ijk.T), tuple(ijk.max(axis=0) + 1))
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        centres = (
            np.stack([np.bincount(inverse, xyz[:, a] - origin[a]) for a in range(3)], axis=1)
            / counts[:, None]
        )
        cells, back = np.unique(inverse[query], return_inverse=True)
    else:
        centres, cells, back = xyz - origin, query, np.arange(len(query))
    tree = cKDTree(centres)
    k = int(min(k, len(centres)))
    cell_normal = np.zeros((len(cells), 3))
    cell_ok = np.zeros(len(cells), dtype=bool)
    for a in range(0, len(cells), chunk):
        q = centres[cells[a : a + chunk]]
        _, nb = tree.query(q, k=k, workers=-1)
        d = centres[nb.reshape(len(q), k)]
        d = d - d.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", d, d)
        val, vec = np.linalg.eigh(cov)  # ascending eigenvalues
        n = vec[:, :, 0]
        n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
        cell_normal[a : a + chunk] = n
        cell_ok[a : a + chunk] = (val[:, 1] >= 4.0 * val[:, 0]) & (val[:, 1] >= 0.01 * val[:, 2])
    normals[:] = cell_normal[back]
    reliable[:] = cell_ok[back]
    return normals, reliable


@dataclass
class RoadModel:
    """Road height along the trajectory."""

    bin_stations: np.ndarray  # (B,) station of each bin centre
    road_height: np.ndarray  # (B,) z of the road surface at each bin centre
    measured: np.ndarray  # (B,) bool: the bin had road points near the trajectory
    mount_height: float  # median sensor-to-road height over the measured bins

    def height(self, station: np.ndarray) -> np.ndarray:
        return np.interp(station, self.bin_stations, self.road_height)

    def bin_of(self, station: np.ndarray) -> np.ndarray:
        """Index of the bin each station falls in (clamped)."""
        step = self.bin_stations[1] - self.bin_stations[0] if len(self.bin_stations) > 1 else 1.0
        b = np.floor((station - self.bin_stations[0]) / step + 0.5)
        return np.clip(b, 0, len(self.bin_stations) - 1).astype(np.int64)


@dataclass
class RoadRemoval:
    """What `road_removal` decided per point, and the station and lateral offset it used."""

    keep: np.ndarray  # (N,) bool
    road: np.ndarray  # (N,) bool: road surface (at/below road height, normal near z)
    ground: np.ndarray  # (N,) bool: other horizontal ground (sidewalks, verges)
    far: np.ndarray  # (N,) bool: too far from the road
    station: np.ndarray  # (N,) float64
    lateral: np.ndarray  # (N,) float64, left positive
    model: RoadModel
    above_ground: np.ndarray  # (N,) float64 height above the local ground (estimate_ground)


def estimate_road(
    xyz: np.ndarray,
    station: np.ndarray,
    lateral: np.ndarray,
    positions: np.ndarray,
    station_bin: float = 1.0,
    corridor: float = 1.5,
    road_percentile: float = 10.0,
    mount_height: float = 2.0,
) -> RoadModel:
    """Road height per station from the lowest points under and around the trajectory."""
    length = float(arc_length(positions)[-1]) if len(positions) > 1 else 0.0
    lo = min(float(np.floor(station.min() / station_bin)) if len(station) else 0.0, 0.0)
    hi = max(float(np.ceil(station.max() / station_bin)) if len(station) else 0.0, length)
    edges0 = lo * station_bin if lo < 0 else 0.0
    n_bins = max(int(np.ceil((hi - edges0) / station_bin)) + 1, 1)
    centres = edges0 + (np.arange(n_bins) + 0.5) * station_bin
    sensor_z = trajectory_height(positions, centres)

    near = np.abs(lateral) <= corridor
    b = np.floor((station[near] - edges0) / station_bin).astype(np.int64)
    inside = (b >= 0) & (b < n_bins)
    z = xyz[near, 2][inside]
    b = b[inside]
    below = z < sensor_z[b]  # the road is below the sensor (drops bridges, tunnel roofs)
    z, b = z[below], b[below]
    road = np.full(n_bins, np.nan)
    if len(z):
        order = np.lexsort((z, b))
        bins, start, count = np.unique(b[order], return_index=True, return_counts=True)
        pick = start + np.floor(road_percentile / 100.0 * (count - 1)).astype(np.int64)
        road[bins] = z[order[pick]]
    measured = ~np.isnan(road)
    offset = sensor_z - road
    mount = float(np.median(offset[measured])) if measured.any() else float(mount_height)
    road = np.where(measured, road, sensor_z - mount)
    if n_bins >= 3:  # a 3-bin median: one bin of curb or car bottom does not dent the road
        road = ndimage.median_filter(road, size=3, mode="nearest")
    return RoadModel(centres, road, measured, mount)


def _road_edges(
    station: np.ndarray, lateral: np.ndarray, road: np.ndarray, model: RoadModel, window: int
) -> np.ndarray:
    """(B, 2) outermost |lateral| of road points per bin on the right (0) and left (1) side,
    the maximum over `window` bins each way; nan where a side has no road point."""
    edges = np.full((len(model.bin_stations), 2), -np.inf)
    b = model.bin_of(station[road])
    side = (lateral[road] > 0).astype(np.int64)
    np.maximum.at(edges, (b, side), np.abs(lateral[road]))
    if window > 0:
        edges = ndimage.maximum_filter1d(edges, size=2 * window + 1, axis=0, mode="nearest")
    edges[~np.isfinite(edges)] = np.nan
    return edges


def road_removal(
    xyz_world: np.ndarray,
    trajectory_positions: np.ndarray,
    *,
    road_tolerance: float = 0.1,  # paper: z <= road height (0); 0.1 m covers camber and noise
    normal_angle_deg: float = 20.0,  # paper: "close to the Z axis" (no number given)
    normal_k: int = 10,  # neighbours for the normal (paper: "neighbor points")
    normal_voxel: float | None = 0.1,  # neighbours among voxel centroids (see point_normals)
    ground_tolerance: float | None = 0.25,  # beyond the paper: also sidewalks; None: road only
    ground_cell: float = 1.0,
    road_margin: float | None = 2.0,  # paper: "points away from road surfaces" (no number)
    max_lateral: float = 15.0,  # hard cap from the trajectory (m)
    edge_window: float = EDGE_WINDOW,  # metres of station: the road edge is the outermost there
    station_bin: float = STATION_BIN,
    corridor: float = 1.5,
    road_percentile: float = 10.0,
    mount_height: float = 2.0,  # only when no road point is seen near the trajectory at all
    station_index: StationIndex | None = None,
    origin: np.ndarray | None = None,
) -> RoadRemoval:
    """Road removal with everything it computed (see the module docstring for the rules).
    `origin` (default: the points' mean) anchors the ground cells and the normals' voxels: a
    tile passes the whole survey's mean, so its cells are the whole survey's. The results
    depend on where the cells fall (on simulated streets the slice F of the classifier moved by
    up to 2 points with the anchor), so a tile must not anchor them anywhere else."""
    xyz = np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3)
    positions = as_positions(trajectory_positions)
    n = len(xyz)
    empty = np.zeros(n, dtype=bool)
    index = StationIndex(positions) if station_index is None else station_index
    if n == 0:
        model = estimate_road(xyz, np.zeros(0), np.zeros(0), positions)
        zero = np.zeros(0)
        return RoadRemoval(empty, empty, empty, empty, zero, zero, model, zero)
    station, lateral = index.query(xyz)
    model = estimate_road(
        xyz, station, lateral, positions, station_bin, corridor, road_percentile, mount_height
    )
    road_z = model.height(station)
    low = xyz[:, 2] <= road_z + road_tolerance
    candidate = low.copy()
    origin = xyz.mean(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
    ground = estimate_ground(xyz - origin, cell=ground_cell)
    above_ground = (xyz[:, 2] - origin[2]) - ground.height(xyz - origin)
    if ground_tolerance is not None:
        candidate |= above_ground <= ground_tolerance
    cand = np.flatnonzero(candidate)
    normals, reliable = point_normals(xyz, cand, k=normal_k, voxel=normal_voxel, origin=origin)
    flat = np.zeros(n, dtype=bool)
    flat[cand] = reliable & (normals[:, 2] >= np.cos(np.radians(normal_angle_deg)))
    road = flat & low
    ground_pts = flat & ~road
    if ground_tolerance is not None:
        ground_pts &= above_ground <= ground_tolerance
    else:
        ground_pts[:] = False

    far = np.abs(lateral) > max_lateral
    if road_margin is not None and road.any():
        window = int(round(edge_window / station_bin))
        edges = _road_edges(station, lateral, road, model, window)
        edge = edges[model.bin_of(station), (lateral > 0).astype(np.int64)]
        with np.errstate(invalid="ignore"):
            far |= np.abs(lateral) > edge + road_margin  # nan edge: comparison is False
    keep = ~(road | ground_pts | far)
    return RoadRemoval(keep, road, ground_pts, far, station, lateral, model, above_ground)


def remove_road(
    xyz_world: np.ndarray, trajectory_positions: np.ndarray, **params: object
) -> np.ndarray:
    """(N,) bool: True for the points that stay (not road, not ground, near the road).

    `trajectory_positions`: (M, 3) sensor positions or (M, 4, 4) sensor poses in drive order.
    Keyword parameters: see `road_removal`.
    """
    return road_removal(xyz_world, trajectory_positions, **params).keep  # type: ignore[arg-type]
