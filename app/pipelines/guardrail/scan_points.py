"""A survey's points with their cell on the scanner's 2D lattice (paper 3.1, after Kohira &
Masuda 2017): what `components` joins into a wireframe.

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
  - otherwise the elevation angle, snapped to the nearest beam elevation (`elevations`: the
    survey's recorded scanner parameters where it has them, as the simulator's varied rotating
    scanners do, 32 or 64 beams and 0.09-0.35 degree steps; HDL-64E's otherwise). The
    simulator (and KITTI) deliver motion-compensated scans: the sensor moved up to ~0.5 m during
    the sweep, which bends near elevations by several beams, so when the points have times the
    ray is taken from the sensor position at the point's time (frame poses interpolated) to the
    point. Checked on simulated HDL-64E frames: the snapped ring is off by at most 0.29 beam
    spacings after this correction, by up to 0.5 (ambiguous) without it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from app.io.survey import Survey

# HDL-64E as simulated (app.simulate.scanners.HDL64Config): 64 beams from +2 to -24.8 degrees
HDL64_ELEVATIONS_DEG = np.linspace(2.0, -24.8, 64)
HDL64_COLUMNS = 4000  # azimuth steps of 0.09 degrees
HDL64_RATE_HZ = 10.0
PROFILE_RATE_HZ = 100.0  # profiles per second (RIEGL VQ-250 in the paper: 100 Hz)
PROFILE_POINTS_PER_S = 300_000.0  # measurements per second (paper: 300,000)
CLOCK_FRAMES = 5  # frames the points' clock offset is measured on (`_clock_offset`)


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


def rotating_layout(survey: Survey) -> tuple[np.ndarray, int, float]:
    """(beam elevations in degrees, azimuth columns, revolutions per second) of the survey's
    rotating scanner: its recorded parameters (`Survey.scanner_params`, beams spaced uniformly
    as the simulator's are), else HDL-64E's. A 32-beam or coarser scanner put on HDL-64E's
    lattice breaks its surfaces into thousands of fragments (the wireframe misses the
    neighbours)."""
    p = survey.scanner_params or {}
    if not {"beams", "elevation_max_deg", "elevation_min_deg", "azimuth_step_deg"} <= p.keys():
        return HDL64_ELEVATIONS_DEG, HDL64_COLUMNS, HDL64_RATE_HZ
    elevations = np.linspace(
        float(p["elevation_max_deg"]), float(p["elevation_min_deg"]), int(p["beams"])
    )
    columns = int(round(360.0 / float(p["azimuth_step_deg"])))
    return elevations, columns, float(p.get("rate_hz", HDL64_RATE_HZ))


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
    elevations_deg: np.ndarray | None = None,
    columns: int | None = None,
    rate_hz: float | None = None,
    motion_compensated: bool = True,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
) -> ScanPoints:
    """Every point of the survey in world coordinates, with its lattice cell when recoverable.

    `scanner` defaults to `survey.scanner`. Profile: needs per-point times. HDL-64 (or an
    unknown scanner on a multi-frame survey): rings from point order or elevation, columns from
    time or azimuth; the beams, columns and rate not given come from `rotating_layout`. A
    single accumulated map without a profile scanner's times gets no lattice. `keep` (world
    xyz -> bool mask, e.g. a tile's window) drops points frame by frame, after their lattice
    cells are known: a frame's rings come from all its points.
    """
    scanner = scanner or survey.scanner  # type: ignore[assignment]
    layout = rotating_layout(survey)
    elevations_deg = layout[0] if elevations_deg is None else elevations_deg
    columns = layout[1] if columns is None else columns
    rate_hz = layout[2] if rate_hz is None else rate_hz
    picked = list(range(len(survey))) if frames is None else list(frames)
    # the clock offset from the first frames (it is one per survey); the frames are then read
    # one at a time: a tile's frames together can hold far more points than its window keeps
    first = [survey.frames[i] for i in picked[:CLOCK_FRAMES]]
    times = [f.points().time for f in first]
    has_time = all(t is not None for t in times) and len(picked) > 0
    xyz, fr, idx, tt, inten = [], [], [], [], []
    rows, cols, sweeps = [], [], []
    rotating = scanner == "hdl64" or (scanner is None and not survey.is_map)
    rotating = rotating and scanner != "profile"
    offset = _clock_offset(first, times) if has_time else 0.0
    poses = survey.poses()
    stamps = [f.timestamp for f in survey.frames]
    frame_times = np.array(stamps, dtype=np.float64) if None not in stamps else None
    for j, i in enumerate(picked):
        cloud = survey.frames[i].points()
        if has_time and cloud.time is None:
            raise ValueError(f"{survey.source}: frame {survey.frames[i].frame_id} has no point "
                             "times where the frames before it have")  # fmt: skip
        pose = survey.frames[i].pose
        world = cloud.xyz @ pose[:3, :3].T + pose[:3, 3]
        sel = slice(None) if keep is None else np.asarray(keep(world), dtype=bool)
        xyz.append(world[sel])
        n = len(xyz[-1])
        fr.append(np.full(n, i, dtype=np.int32))
        idx.append(np.arange(len(cloud), dtype=np.int64)[sel])
        if has_time:
            tt.append(np.asarray(cloud.time, dtype=np.float64)[sel])
        if cloud.intensity is not None:
            inten.append(np.asarray(cloud.intensity, dtype=np.float32)[sel])
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
            rows.append(ring[sel])
            cols.append(col[sel])
            sweeps.append(np.full(n, j, dtype=np.int64))
    points = ScanPoints(
        xyz=np.concatenate(xyz) if xyz else np.zeros((0, 3)),
        frame=np.concatenate(fr) if fr else np.zeros(0, np.int32),
        index=np.concatenate(idx) if idx else np.zeros(0, np.int64),
        time=np.concatenate(tt) if has_time else None,
        intensity=np.concatenate(inten) if len(inten) == len(picked) and inten else None,
    )
    if rotating and rows:
        points.lattice = Lattice(
            np.concatenate(sweeps), np.concatenate(rows), np.concatenate(cols), columns, "rotating"
        )
    elif scanner == "profile" and points.time is not None:
        points.lattice = profile_lattice(points.time, profiles_per_s, points_per_s)
    return points
