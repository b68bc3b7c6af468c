"""Connected components on the scanner's 2D lattice (paper 3.1, after Kohira & Masuda 2017).

An MMS scanner fires on a regular pattern, so every point has a cell on a 2D lattice; joining
lattice neighbours gives a wireframe of the scanned surfaces, and its connected components are
the roadside objects. Two neighbours are joined only when their 3D distance is within `max_edge`,
so a depth jump (a car in front of a guardrail, a pole in front of a wall) cuts the wireframe.

Lattices:

- **Profile scanner** (RIEGL VQ-250-like, `app.simulate.scanners.ProfileConfig`): row = profile
  number `floor(t * profiles_per_s)`, column = step in the profile
  `round((t - row / profiles_per_s) * points_per_s)` (wraps around: the profile is a full
  circle). One lattice for the whole drive: consecutive profiles are consecutive rows, across
  frames. Only the per-point time and the two rates are needed.
- **Rotating scanner** (HDL-64E): one lattice per revolution (frame); row = ring (beam),
  column = azimuth step (wraps). The column comes from the time when the points have one
  (`(t - sweep start) * rate_hz * columns`, the sweep starting half a revolution before the
  frame's timestamp, KITTI's convention) and from the azimuth otherwise. Time does not give the
  ring (all beams fire together); it comes from
  - the point order when the file is ring-major, as KITTI's velodyne `.bin` files are: each
    ring is stored as one sweep that starts facing forward, so a new ring starts wherever the
    azimuth crosses from negative to non-negative in front of the car (x > 0); checked on the
    real KITTI raw and SemanticKITTI scans in `../shared/data` (exactly 63 such crossings per
    scan, ring elevations strictly decreasing);
  - otherwise the elevation angle, snapped to the nearest beam elevation (`elevations`). The
    simulator (and KITTI) deliver motion-compensated scans: the sensor moved up to ~0.5 m during
    the sweep, which bends near elevations by several beams, so when the points have times the
    ray is taken from the sensor position at the point's time (frame poses interpolated) to the
    point. Checked on simulated HDL-64E frames: the snapped ring is off by at most 0.29 beam
    spacings after this correction, by up to 0.5 (ambiguous) without it.
  Consecutive revolutions see the same objects: a point is also joined to its nearest point of
  the previous revolution when that is within `max_edge`.

Neighbourhood: along a row, the next `col_window` cells; across to the next row, columns within
+-`row_col_window`. Wider than the paper's 4-neighbourhood because thin diagonal pipes move
several steps between consecutive profiles and would otherwise break into pieces. Fragments
smaller than `min_points` are attached to the nearest larger component within `attach_distance`.
Points less than `min_height` above the ground (curb faces, sidewalk edges that the road removal
leaves because they are not horizontal) make no edges to higher points and join the component of
the nearest higher point within `max_edge` afterwards: otherwise the curb chains every guardrail
to the cars parked along it (seen on the simulated HDL-64E survey).

**Fallback**: without a lattice (LAS/PLY maps without time, unknown scanner) Euclidean
clustering: points within `cluster_tolerance` are connected, computed on voxel centroids
(voxel = tolerance / 2) with a KD-tree pair search so dense surfaces stay cheap.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components as _csgraph_components
from scipy.spatial import cKDTree

from app.io.survey import Survey

# HDL-64E as simulated (app.simulate.scanners.HDL64Config): 64 beams from +2 to -24.8 degrees
HDL64_ELEVATIONS_DEG = np.linspace(2.0, -24.8, 64)
HDL64_COLUMNS = 4000  # azimuth steps of 0.09 degrees
HDL64_RATE_HZ = 10.0
PROFILE_RATE_HZ = 100.0  # profiles per second (RIEGL VQ-250 in the paper: 100 Hz)
PROFILE_POINTS_PER_S = 300_000.0  # measurements per second (paper: 300,000)


@dataclass
class Lattice:
    """The lattice cell of each point: `sweep` (revolution; 0 for a profile scanner), `row`
    (profile / ring) and `col` (step / azimuth column, wrapping at `n_cols`)."""

    sweep: np.ndarray  # (N,) int64
    row: np.ndarray  # (N,) int64
    col: np.ndarray  # (N,) int64
    n_cols: int
    kind: Literal["profile", "rotating"]

    def __len__(self) -> int:
        return len(self.row)

    def take(self, sel: np.ndarray) -> Lattice:
        return Lattice(self.sweep[sel], self.row[sel], self.col[sel], self.n_cols, self.kind)


@dataclass
class ScanPoints:
    """All points of a survey in world coordinates, with where they came from."""

    xyz: np.ndarray  # (N, 3) float64 world
    frame: np.ndarray  # (N,) int32 frame index in the survey
    index: np.ndarray  # (N,) int64 point index within its frame (file order)
    time: np.ndarray | None  # (N,) float64 per-point time (the points' clock), when known
    lattice: Lattice | None = None
    intensity: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class Components:
    """Component id per point (-1: not a candidate, i.e. removed before) and how they were made."""

    label: np.ndarray  # (N,) int32
    count: int
    method: Literal["lattice", "euclidean"]
    sizes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


# ---------------------------------------------------------------------------------- lattices


def profile_lattice(
    time: np.ndarray,
    profiles_per_s: float = PROFILE_RATE_HZ,
    points_per_s: float = PROFILE_POINTS_PER_S,
    time_offset: float = 0.0,
) -> Lattice:
    """Profile scanner: (profile number, step) from the per-point time and the two rates.

    Profile k starts at `time_offset + k / profiles_per_s`; its step s fires `s / points_per_s`
    later (points_per_s / profiles_per_s steps per profile, back to back). Rows count from the
    first profile.
    """
    t = np.asarray(time, dtype=np.float64) - time_offset
    n_cols = int(round(points_per_s / profiles_per_s))
    if len(t) == 0:
        z = np.zeros(0, dtype=np.int64)
        return Lattice(z, z, z, n_cols, "profile")
    # profile k, step s fires at (k * n_cols + s) / points_per_s: one global step count, rounded
    # (half a step of tolerance, far above float64 resolution at GPS-sized seconds)
    t0 = np.floor(t.min() * profiles_per_s) / profiles_per_s
    n = np.round((t - t0) * points_per_s).astype(np.int64)
    row, col = np.divmod(n, n_cols)
    return Lattice(np.zeros(len(t), dtype=np.int64), row, col, n_cols, "profile")


def rings_from_order(xyz_sensor: np.ndarray, beams: int = 64) -> np.ndarray | None:
    """Rings of a ring-major scan (KITTI .bin): a new ring at each forward azimuth crossing
    from negative to non-negative. None when the count of crossings is not `beams - 1`."""
    x, y = xyz_sensor[:, 0], xyz_sensor[:, 1]
    if len(x) < 2:
        return None
    crossing = (y[:-1] < 0) & (y[1:] >= 0) & (x[1:] > 0)
    if int(crossing.sum()) != beams - 1:
        return None
    return np.concatenate([[0], np.cumsum(crossing)]).astype(np.int64)


def rings_from_elevation(
    xyz_sensor: np.ndarray, elevations_deg: np.ndarray, origin: np.ndarray | None = None
) -> np.ndarray:
    """Nearest beam elevation of each ray (from `origin`, (N, 3) or None = sensor origin)."""
    ray = xyz_sensor if origin is None else xyz_sensor - origin
    elev = np.degrees(np.arctan2(ray[:, 2], np.hypot(ray[:, 0], ray[:, 1])))
    table = np.asarray(elevations_deg, dtype=np.float64)
    order = np.argsort(table)
    sorted_el = table[order]
    j = np.clip(np.searchsorted(sorted_el, elev), 1, len(table) - 1)
    nearer_low = (elev - sorted_el[j - 1]) < (sorted_el[j] - elev)
    return order[np.where(nearer_low, j - 1, j)].astype(np.int64)


def rotating_frame_lattice(
    xyz_sensor: np.ndarray,
    time: np.ndarray | None = None,
    sweep_start: float | None = None,
    origin: np.ndarray | None = None,
    elevations_deg: np.ndarray = HDL64_ELEVATIONS_DEG,
    columns: int = HDL64_COLUMNS,
    rate_hz: float = HDL64_RATE_HZ,
    ring_from: Literal["auto", "order", "elevation"] = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """(ring, column) of one revolution's points (see the module docstring).

    `origin`: (N, 3) sensor position at each point's time in this frame's sensor coordinates
    (undoes motion compensation for the elevation); `sweep_start` on the points' clock.
    """
    ring = None
    if ring_from in ("auto", "order"):
        ring = rings_from_order(xyz_sensor, len(elevations_deg))
        if ring is None and ring_from == "order":
            raise ValueError("the scan is not ring-major (azimuth crossings != beams - 1)")
    if ring is None:
        ring = rings_from_elevation(xyz_sensor, elevations_deg, origin)
    if time is not None and sweep_start is not None:
        frac = (np.asarray(time) - sweep_start) * rate_hz
    else:
        ray = xyz_sensor if origin is None else xyz_sensor - origin
        frac = 0.5 * (-np.arctan2(ray[:, 1], ray[:, 0]) / np.pi + 1.0)  # KITTI sweep fraction
    col = np.mod(np.round(frac * columns).astype(np.int64), columns)
    return ring, col


def _clock_offset(frames: list, times: list[np.ndarray | None]) -> float:
    """Seconds to add to the points' times to get the frames' timestamps (0 when they agree).

    The simulator writes per-point times in simulation seconds but frame timestamps as dates."""
    diffs = [
        f.timestamp - 0.5 * (t.min() + t.max())
        for f, t in zip(frames, times, strict=True)
        if f.timestamp is not None and t is not None and len(t)
    ]
    if not diffs:
        return 0.0
    off = float(np.median(diffs))
    return round(off, 3) if abs(off) > 0.5 else 0.0


def _sensor_origins(
    times: np.ndarray, frame_times: np.ndarray, positions: np.ndarray, pose: np.ndarray
) -> np.ndarray:
    """Sensor position at each time (linear between frame poses) in `pose`'s sensor frame."""
    world = np.stack([np.interp(times, frame_times, positions[:, a]) for a in range(3)], axis=1)
    inv_R = pose[:3, :3].T
    return (world - pose[:3, 3]) @ inv_R.T


def load_scan_points(
    survey: Survey,
    scanner: Literal["profile", "hdl64"] | None = None,
    frames: list[int] | None = None,
    profiles_per_s: float = PROFILE_RATE_HZ,
    points_per_s: float = PROFILE_POINTS_PER_S,
    elevations_deg: np.ndarray = HDL64_ELEVATIONS_DEG,
    columns: int = HDL64_COLUMNS,
    rate_hz: float = HDL64_RATE_HZ,
    motion_compensated: bool = True,
) -> ScanPoints:
    """Every point of the survey in world coordinates, with its lattice cell when recoverable.

    `scanner` defaults to `survey.scanner`. Profile: needs per-point times. HDL-64 (or an
    unknown scanner on a multi-frame survey): rings from point order or elevation, columns from
    time or azimuth. A single accumulated map without a profile scanner's times gets no lattice.
    """
    scanner = scanner or survey.scanner  # type: ignore[assignment]
    picked = list(range(len(survey))) if frames is None else list(frames)
    clouds = [survey.frames[i].points() for i in picked]
    times = [c.time for c in clouds]
    has_time = all(t is not None for t in times) and len(clouds) > 0
    xyz, fr, idx, tt, inten = [], [], [], [], []
    rows, cols, sweeps = [], [], []
    rotating = scanner == "hdl64" or (scanner is None and not survey.is_map)
    rotating = rotating and scanner != "profile"
    offset = _clock_offset([survey.frames[i] for i in picked], times) if has_time else 0.0
    poses = survey.poses()
    stamps = [f.timestamp for f in survey.frames]
    frame_times = np.array(stamps, dtype=np.float64) if None not in stamps else None
    for j, (i, cloud) in enumerate(zip(picked, clouds, strict=True)):
        pose = survey.frames[i].pose
        xyz.append(cloud.xyz @ pose[:3, :3].T + pose[:3, 3])
        fr.append(np.full(len(cloud), i, dtype=np.int32))
        idx.append(np.arange(len(cloud), dtype=np.int64))
        if has_time:
            tt.append(np.asarray(cloud.time, dtype=np.float64))
        if cloud.intensity is not None:
            inten.append(np.asarray(cloud.intensity, dtype=np.float32))
        if rotating:
            origin = None
            sweep_start = None
            if has_time and frame_times is not None:
                t_pts = np.asarray(cloud.time) + offset
                sweep_start = float(frame_times[i]) - 0.5 / rate_hz
                if motion_compensated and len(frame_times) > 1:
                    origin = _sensor_origins(t_pts, frame_times, poses[:, :3, 3], pose)
                ring, col = rotating_frame_lattice(
                    cloud.xyz, t_pts, sweep_start, origin, elevations_deg, columns, rate_hz
                )
            else:
                ring, col = rotating_frame_lattice(
                    cloud.xyz, None, None, None, elevations_deg, columns, rate_hz
                )
            rows.append(ring)
            cols.append(col)
            sweeps.append(np.full(len(cloud), j, dtype=np.int64))
    points = ScanPoints(
        xyz=np.concatenate(xyz) if xyz else np.zeros((0, 3)),
        frame=np.concatenate(fr) if fr else np.zeros(0, np.int32),
        index=np.concatenate(idx) if idx else np.zeros(0, np.int64),
        time=np.concatenate(tt) if has_time else None,
        intensity=np.concatenate(inten) if len(inten) == len(clouds) and inten else None,
    )
    if rotating and rows:
        points.lattice = Lattice(
            np.concatenate(sweeps), np.concatenate(rows), np.concatenate(cols), columns, "rotating"
        )
    elif scanner == "profile" and points.time is not None:
        points.lattice = profile_lattice(points.time, profiles_per_s, points_per_s)
    return points


# ------------------------------------------------------------------------------- components


def _lattice_offsets(col_window: int, row_col_window: int) -> np.ndarray:
    """(row, col) offsets to the 'forward' half of the neighbourhood (each edge found once)."""
    along = [(0, c) for c in range(1, col_window + 1)]
    across = [(1, c) for c in range(-row_col_window, row_col_window + 1)]
    return np.array(along + across, dtype=np.int64).reshape(-1, 2)


def wireframe_edges(
    xyz: np.ndarray,
    lattice: Lattice,
    max_edge: float = 0.3,
    col_window: int = 2,
    row_col_window: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) point pairs that are lattice neighbours and within `max_edge` in 3D.

    Cells are looked up in a dense table (one int per lattice cell) when the lattice is not much
    larger than the point count, else by binary search in the sorted cell keys.
    """
    n = len(xyz)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    n_cols = lattice.n_cols
    row0 = int(lattice.row.min())
    n_rows = int(lattice.row.max()) - row0 + 2  # one free row: row + 1 never reaches a sweep
    sweep0 = int(lattice.sweep.min())
    rows = lattice.row - row0
    base = ((lattice.sweep - sweep0) * n_rows + rows) * n_cols
    key = base + lattice.col
    n_keys = (int(lattice.sweep.max()) - sweep0 + 1) * n_rows * n_cols  # free row included
    ii, jj = [], []
    if n_keys <= max(16 * n, 1 << 24):
        table = np.full(n_keys, -1, dtype=np.int64)
        table[key] = np.arange(n)
        owner = table[key]
        dup = np.flatnonzero(owner != np.arange(n))  # cells holding two points: join them
        ii.append(dup)
        jj.append(owner[dup])

        def lookup(nkey: np.ndarray) -> np.ndarray:
            return table[nkey]

    else:
        order = np.argsort(key, kind="stable")
        skey = key[order]
        same = np.flatnonzero(skey[1:] == skey[:-1])
        ii.append(order[same])
        jj.append(order[same + 1])

        def lookup(nkey: np.ndarray) -> np.ndarray:
            at = np.minimum(np.searchsorted(skey, nkey), n - 1)
            return np.where(skey[at] == nkey, order[at], -1)

    for dr, dc in _lattice_offsets(col_window, row_col_window):
        nkey = base + dr * n_cols + np.mod(lattice.col + dc, n_cols)
        j = lookup(nkey)
        src = np.flatnonzero(j >= 0)
        ii.append(src)
        jj.append(j[src])
    i = np.concatenate(ii)
    j = np.concatenate(jj)
    diff = xyz[i] - xyz[j]
    ok = np.einsum("ij,ij->i", diff, diff) <= max_edge**2
    return i[ok], j[ok]


def _sweep_edges(
    xyz: np.ndarray, sweep: np.ndarray, max_edge: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each point to its nearest point of the previous sweep, when within max_edge."""
    ii, jj = [], []
    ids = np.unique(sweep)
    groups = {int(s): np.flatnonzero(sweep == s) for s in ids}
    for a, b in zip(ids[:-1], ids[1:], strict=True):
        prev, cur = groups[int(a)], groups[int(b)]
        if len(prev) == 0 or len(cur) == 0:
            continue
        tree = cKDTree(xyz[prev])
        d, nb = tree.query(xyz[cur], k=1, distance_upper_bound=max_edge, workers=-1)
        ok = np.isfinite(d)
        ii.append(cur[ok])
        jj.append(prev[nb[ok]])
    if not ii:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(ii), np.concatenate(jj)


def euclidean_edges(xyz: np.ndarray, tolerance: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Edges of Euclidean clustering, on voxel centroids: returns (point, point) pairs that tie
    each point to its voxel's first point and voxels whose centroids are within `tolerance`."""
    n = len(xyz)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    voxel = tolerance / 2.0
    local = xyz - xyz.min(axis=0)
    ijk = np.floor(local / voxel).astype(np.int64)
    _, first, inverse = np.unique(ijk, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse)
    centres = np.stack([np.bincount(inverse, local[:, a]) for a in range(3)], axis=1)
    centres /= counts[:, None]
    pairs = cKDTree(centres).query_pairs(tolerance, output_type="ndarray")
    i = np.concatenate([np.arange(n), first[pairs[:, 0]]])
    j = np.concatenate([first[inverse], first[pairs[:, 1]]])
    return i, j


def _label(n: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    graph = coo_matrix((np.ones(len(i), dtype=np.int8), (i, j)), shape=(n, n))
    _, label = _csgraph_components(graph, directed=False)
    return label.astype(np.int64)


def _attach_fragments(
    xyz: np.ndarray,
    label: np.ndarray,
    min_points: int,
    distance: float,
    eligible: np.ndarray | None = None,
) -> np.ndarray:
    """Fragments smaller than min_points take the label of the nearest larger component within
    `distance` (each fragment as a whole, by its point nearest to one); only `eligible` points
    (default all) take part, as fragments or as targets."""
    sizes = np.bincount(label)
    small = sizes[label] < min_points
    ok_pts = np.ones(len(label), dtype=bool) if eligible is None else eligible
    big = np.flatnonzero(~small & ok_pts)
    frag = np.flatnonzero(small & ok_pts)
    if len(big) == 0 or len(frag) == 0:
        return label
    d, nb = cKDTree(xyz[big]).query(xyz[frag], k=1, distance_upper_bound=distance, workers=-1)
    ok = np.isfinite(d)
    if not ok.any():
        return label
    frag, d, target = frag[ok], d[ok], label[big[nb[ok]]]
    order = np.lexsort((d, label[frag]))  # per fragment, nearest first
    flab = label[frag][order]
    first = np.concatenate([[True], flab[1:] != flab[:-1]])
    mapping = np.arange(len(sizes))
    mapping[flab[first]] = target[order][first]
    return mapping[label]


def _attach_low(xyz: np.ndarray, label: np.ndarray, low: np.ndarray, distance: float) -> np.ndarray:
    """Each low point takes the label of its nearest high point within `distance`."""
    high = np.flatnonzero(~low)
    lows = np.flatnonzero(low)
    d, nb = cKDTree(xyz[high]).query(xyz[lows], k=1, distance_upper_bound=distance, workers=-1)
    ok = np.isfinite(d)
    label = label.copy()
    label[lows[ok]] = label[high[nb[ok]]]
    return label


def connected_components(
    points: ScanPoints | np.ndarray,
    keep: np.ndarray | None = None,
    *,
    lattice: Lattice | None = None,
    max_edge: float = 0.3,  # paper: lattice neighbours are connected (no distance given)
    col_window: int = 2,
    row_col_window: int = 3,
    link_sweeps: bool = True,
    cluster_tolerance: float = 0.3,
    min_points: int = 10,
    attach_distance: float = 0.5,
    above_ground: np.ndarray | None = None,
    min_height: float = 0.25,
) -> Components:
    """Connected components of the kept points (paper 3.1).

    `points`: `ScanPoints` from `load_scan_points` (its lattice is used) or an (N, 3) world
    array (then `lattice` may be given, else Euclidean clustering). `keep`: (N,) bool, e.g.
    `remove_road(...)`; removed points get label -1. Labels are 0..count-1, largest first.

    `above_ground` (N,) (e.g. `RoadRemoval.above_ground`): points lower than `min_height` make
    no edges to higher points; each joins the component of its nearest higher point within
    `max_edge`, the rest stay connected among themselves. Without this, curbs and sidewalk
    edges (left by the road removal: not horizontal) chain guardrails to parked cars.
    """
    if isinstance(points, ScanPoints):
        xyz = points.xyz
        lattice = points.lattice if lattice is None else lattice
    else:
        xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n_all = len(xyz)
    sel = np.arange(n_all) if keep is None else np.flatnonzero(keep)
    sub = xyz[sel]
    local = sub - sub.mean(axis=0) if len(sub) else sub
    method: Literal["lattice", "euclidean"] = "lattice" if lattice is not None else "euclidean"
    if lattice is not None:
        lat = lattice.take(sel)
        i, j = wireframe_edges(local, lat, max_edge, col_window, row_col_window)
        if link_sweeps and lat.kind == "rotating" and len(np.unique(lat.sweep)) > 1:
            si, sj = _sweep_edges(local, lat.sweep, max_edge)
            i, j = np.concatenate([i, si]), np.concatenate([j, sj])
    else:
        i, j = euclidean_edges(local, cluster_tolerance)
    low = None
    if above_ground is not None and len(sub):
        low = np.asarray(above_ground, dtype=np.float64)[sel] < min_height
        mixed = low[i] != low[j]
        i, j = i[~mixed], j[~mixed]
    label = _label(len(sub), i, j) if len(sub) else np.zeros(0, np.int64)
    if min_points > 1 and len(sub):
        eligible = None if low is None else ~low  # low points are attached below
        label = _attach_fragments(local, label, min_points, attach_distance, eligible)
    if low is not None and low.any() and not low.all():
        label = _attach_low(local, label, low, max_edge)
    out = np.full(n_all, -1, dtype=np.int32)
    sizes = np.zeros(0, dtype=np.int64)
    if len(sub):
        counts = np.bincount(label)
        used = np.flatnonzero(counts)
        by_size = used[np.argsort(-counts[used], kind="stable")]
        rank = np.full(len(counts), -1, dtype=np.int64)
        rank[by_size] = np.arange(len(by_size))
        out[sel] = rank[label]
        sizes = counts[by_size]
    return Components(out, int(len(sizes)), method, sizes)
