"""LiDAR scanners: firing patterns (directions and times in the sensor frame) and the scan itself.

Two sensors:

- `HDL64Config`: KITTI's Velodyne HDL-64E, 64 beams, one revolution per 0.1 s. KITTI's sweep
  starts facing backwards (azimuth +pi), turns clockwise seen from above and faces forwards half
  way, so each ray's sweep fraction `0.5 * (-atan2(y, x) / pi + 1)` equals
  `(time - sweep_start) * rate_hz` (`app.io.velodyne_bin.sweep_fraction`).
- `ProfileConfig`: a RIEGL VQ-250-like profile scanner on the rear roof, 100 profiles a second of
  3000 points each, sweeping the sensor's y-z plane (across the driving direction), so the map is
  built line by line as the vehicle drives (the phantom paper's MLS setting).

Sensor frame: x forward, y left, z up. `T_vehicle_sensor` maps sensor to vehicle coordinates
(vehicle frame: x forward, y left, z up, origin on the ground under the vehicle centre, as
`Scene.vehicle_path`). `scan` places the sensor at every ray's own time, casts, and applies the
sensor's range limits, dropouts, range noise and an intensity model; points come out in world
coordinates (float64) with their ground truth (body, triangle, halo).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.simulate.raycast import RayCaster
from app.simulate.scene import Motion, Scene


def _mount(x: float, y: float, z: float, tilt_deg: float = 0.0) -> np.ndarray:
    """4x4 sensor -> vehicle: translation (x, y, z) and a rotation by tilt about the y axis."""
    a = np.radians(tilt_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    T[:3, 3] = (x, y, z)
    return T


@dataclass(frozen=True)
class HDL64Config:
    """Velodyne HDL-64E as mounted on the KITTI car."""

    beams: int = 64
    elevation_max_deg: float = 2.0  # ring 0 (top beam)
    elevation_min_deg: float = -24.8  # ring beams-1; beams spaced uniformly in between
    azimuth_step_deg: float = 0.09  # 4000 columns per revolution
    rate_hz: float = 10.0  # revolutions per second
    min_range: float = 2.0
    max_range: float = 120.0
    range_noise_m: float = 0.02  # sigma of Gaussian range noise
    dropout: float = 0.05  # probability that a return goes missing
    mount_x: float = 0.0  # sensor position in the vehicle frame (m)
    mount_y: float = 0.0
    mount_height: float = 1.73  # KITTI: laser scanner 1.73 m above the ground

    @property
    def columns(self) -> int:
        return int(round(360.0 / self.azimuth_step_deg))

    @property
    def T_vehicle_sensor(self) -> np.ndarray:
        return _mount(self.mount_x, self.mount_y, self.mount_height)

    def elevations(self) -> np.ndarray:
        """Beam elevations (radians), ring 0 first (top)."""
        return np.radians(np.linspace(self.elevation_max_deg, self.elevation_min_deg, self.beams))


@dataclass(frozen=True)
class ProfileConfig:
    """RIEGL VQ-250-like profile scanner: full circles in the plane across the driving direction.

    Step 0 of each profile points straight down; the angle grows towards +y (left), up, then right:
    direction = (0, sin phi, -cos phi), phi = 2 pi step / points_per_profile. A positive `tilt_deg`
    turns the scan plane about the sensor's y (lateral) axis so that upward rays lean forwards.
    """

    profiles_per_s: float = 100.0
    points_per_s: float = 300_000.0  # 3000 per profile: 0.12 deg steps over 360 deg
    min_range: float = 1.5
    max_range: float = 200.0
    range_noise_m: float = 0.008
    dropout: float = 0.02
    mount_x: float = -1.0  # rear roof
    mount_y: float = 0.0
    mount_height: float = 2.4
    tilt_deg: float = 0.0

    @property
    def points_per_profile(self) -> int:
        return int(round(self.points_per_s / self.profiles_per_s))

    @property
    def T_vehicle_sensor(self) -> np.ndarray:
        return _mount(self.mount_x, self.mount_y, self.mount_height, self.tilt_deg)


ScannerConfig = HDL64Config | ProfileConfig


@dataclass
class RayPattern:
    """Rays of a scanner in the SENSOR frame, in firing order (times non-decreasing)."""

    directions: np.ndarray  # (N, 3) float64 unit, sensor frame
    times: np.ndarray  # (N,) float64 absolute seconds
    ring: np.ndarray  # (N,) uint8 beam index (HDL64), 0 for the profile scanner
    column: np.ndarray  # (N,) int32 azimuth column (HDL64) / profile index (profile scanner)
    step: np.ndarray  # (N,) int32 index within the profile (profile scanner) / 0

    def __len__(self) -> int:
        return len(self.times)

    def take(self, sel: slice | np.ndarray) -> RayPattern:
        return RayPattern(
            self.directions[sel], self.times[sel], self.ring[sel], self.column[sel], self.step[sel]
        )


def hdl64_pattern(config: HDL64Config, sweep_start: float) -> RayPattern:
    """One revolution: `columns` firings of all beams, column-major (times non-decreasing).

    Column c fires at sweep_start + c / columns / rate_hz facing azimuth pi - 2 pi c / columns.
    """
    cols = config.columns
    c = np.arange(cols)
    azimuth = np.pi - 2.0 * np.pi * c / cols
    elevation = config.elevations()
    ce = np.cos(elevation)
    directions = np.stack(
        [
            np.outer(np.cos(azimuth), ce),
            np.outer(np.sin(azimuth), ce),
            np.broadcast_to(np.sin(elevation), (cols, config.beams)),
        ],
        axis=-1,
    ).reshape(-1, 3)
    times = np.repeat(sweep_start + c / cols / config.rate_hz, config.beams)
    return RayPattern(
        directions=directions,
        times=times,
        ring=np.tile(np.arange(config.beams, dtype=np.uint8), cols),
        column=np.repeat(c.astype(np.int32), config.beams),
        step=np.zeros(cols * config.beams, dtype=np.int32),
    )


def profile_pattern(config: ProfileConfig, t0: float, t1: float) -> RayPattern:
    """Every profile starting in [t0, t1); profile k starts at k / profiles_per_s, its step s
    fires at that time + s / points_per_s."""
    k0 = int(np.ceil(t0 * config.profiles_per_s - 1e-9))
    k1 = int(np.ceil(t1 * config.profiles_per_s - 1e-9))
    k = np.arange(k0, k1)
    k = k[(k / config.profiles_per_s >= t0) & (k / config.profiles_per_s < t1)]
    m = config.points_per_profile
    s = np.arange(m)
    phi = 2.0 * np.pi * s / m
    ring_dirs = np.stack([np.zeros(m), np.sin(phi), -np.cos(phi)], axis=-1)
    times = (k[:, None] / config.profiles_per_s + s[None, :] / config.points_per_s).reshape(-1)
    return RayPattern(
        directions=np.tile(ring_dirs, (len(k), 1)),
        times=times,
        ring=np.zeros(len(k) * m, dtype=np.uint8),
        column=np.repeat(k.astype(np.int32), m),
        step=np.tile(s.astype(np.int32), len(k)),
    )


@dataclass
class ScanPoints:
    """Simulated returns in world coordinates with their ground truth."""

    xyz_world: np.ndarray  # (N, 3) float64
    time: np.ndarray  # (N,) float64 absolute seconds
    intensity: np.ndarray  # (N,) float32 0..1
    ring: np.ndarray  # (N,) uint8
    column: np.ndarray  # (N,) int32
    step: np.ndarray  # (N,) int32
    body: np.ndarray  # (N,) int32 index into scene.bodies
    triangle: np.ndarray  # (N,) int64 triangle of that body's mesh
    halo: np.ndarray  # (N,) bool laser-bounce halo return
    range: np.ndarray  # (N,) float64 measured range (with noise)

    def __len__(self) -> int:
        return len(self.time)

    @staticmethod
    def concatenate(parts: list[ScanPoints]) -> ScanPoints:
        names = list(ScanPoints.__dataclass_fields__)
        if not parts:
            return _empty_points()
        return ScanPoints(**{f: np.concatenate([getattr(p, f) for p in parts]) for f in names})


def _empty_points() -> ScanPoints:
    return ScanPoints(
        xyz_world=np.zeros((0, 3)),
        time=np.zeros(0),
        intensity=np.zeros(0, dtype=np.float32),
        ring=np.zeros(0, dtype=np.uint8),
        column=np.zeros(0, dtype=np.int32),
        step=np.zeros(0, dtype=np.int32),
        body=np.zeros(0, dtype=np.int32),
        triangle=np.zeros(0, dtype=np.int64),
        halo=np.zeros(0, dtype=bool),
        range=np.zeros(0),
    )


def _rotate(trig: tuple[np.ndarray, ...], v: np.ndarray) -> np.ndarray:
    """`Motion.rotations` (Rz(yaw) @ Ry(-pitch)) applied to vectors (one or one per rotation),
    without building matrices; `trig` = cos(yaw), sin(yaw), cos(pitch), sin(pitch)."""
    cy, sy, cp, sp = trig
    u = cp * v[:, 0] - sp * v[:, 2]
    out = np.empty((len(cy), 3))
    out[:, 0] = cy * u - sy * v[:, 1]
    out[:, 1] = sy * u + cy * v[:, 1]
    out[:, 2] = sp * v[:, 0] + cp * v[:, 2]
    return out


def reflectivities(scene: Scene) -> np.ndarray:
    """Per-body reflectivity (0..1) for the intensity model."""
    return np.array([b.reflectivity for b in scene.bodies], dtype=np.float64)


def scan(
    caster: RayCaster,
    pattern: RayPattern,
    sensor_motion: Motion,
    T_vehicle_sensor: np.ndarray,
    config: ScannerConfig,
    rng: np.random.Generator,
    reflectivity: np.ndarray | None = None,
) -> ScanPoints:
    """Fire `pattern` from a sensor mounted by `T_vehicle_sensor` on a vehicle moving along
    `sensor_motion`; the sensor pose of each ray is the vehicle pose at that ray's time.

    Kept: hits whose true range is within [min_range, max_range] and that survive the random
    dropout. The measured range gets Gaussian noise along the ray. Intensity =
    clip(reflectivity * (0.3 + 0.7 |cos incidence|) * (1 - 0.3 range / max_range) + N(0, 0.02)).
    `reflectivity` defaults to the bodies' `reflectivity` of `caster.scene`.
    """
    refl = reflectivities(caster.scene) if reflectivity is None else np.asarray(reflectivity)
    T = np.asarray(T_vehicle_sensor, dtype=np.float64)
    R_vs, t_vs = T[:3, :3], T[:3, 3]
    parts = []
    for a in range(0, len(pattern), caster.chunk_size):
        p = pattern.take(slice(a, a + caster.chunk_size))
        yaw, pitch = sensor_motion.yaw(p.times), sensor_motion.pitch(p.times)
        trig = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
        origins = _rotate(trig, t_vs[None, :]) + sensor_motion.position(p.times)
        directions = _rotate(trig, p.directions @ R_vs.T)
        hits = caster.cast(origins, directions, p.times, config.max_range, rng)
        keep = (hits.body >= 0) & (hits.distance >= config.min_range)
        keep &= hits.distance <= config.max_range
        keep &= rng.random(len(p)) >= config.dropout
        i = np.flatnonzero(keep)
        dist = hits.distance[i]
        measured = dist + rng.normal(0.0, config.range_noise_m, len(i))
        d = directions[i]
        cos_inc = np.abs(np.einsum("ij,ij->i", hits.normal[i], d))
        body = hits.body[i]
        intensity = refl[body] * (0.3 + 0.7 * cos_inc) * (1.0 - 0.3 * dist / config.max_range)
        intensity = np.clip(intensity + rng.normal(0.0, 0.02, len(i)), 0.0, 1.0)
        parts.append(
            ScanPoints(
                xyz_world=origins[i] + measured[:, None] * d,
                time=p.times[i],
                intensity=intensity.astype(np.float32),
                ring=p.ring[i],
                column=p.column[i],
                step=p.step[i],
                body=body,
                triangle=hits.triangle[i],
                halo=hits.halo[i],
                range=measured,
            )
        )
    return ScanPoints.concatenate(parts)
