"""Simulate a survey: build the street, drive the scanner and camera through it, write it out.

Frames are 0.1 s long (10 Hz, KITTI): a full revolution of the HDL-64E, or 10 profiles of the
profile scanner. Each frame's points are given in the sensor frame at the frame's reference time
(mid-sweep, when the camera fires), as a motion-compensated scanner delivers them; every point
keeps its own time, and moving objects were hit where they were at that time, so they appear as
true phantoms. The camera renders at the reference time.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

from app import __version__
from app.core.errors import InputError
from app.core.labels import Semantic
from app.geometry.transforms import apply, invert, make_transform
from app.simulate import kitti_writer as kw
from app.simulate.camera import CameraConfig, render
from app.simulate.ground_truth import BodyTable, pillar_classes
from app.simulate.layout import build_scene
from app.simulate.raycast import RayCaster
from app.simulate.scanners import HDL64Config, ProfileConfig, hdl64_pattern, profile_pattern, scan
from app.simulate.scene import Scene
from app.simulate.situations import SITUATIONS, build_situation

FRAME_RATE = 10.0  # Hz: scanner frames and camera images
# camera 0.27 m ahead of the roof sensor mast, 1.65 m above the ground (KITTI-like); the
# rotation maps camera axes (x right, y down, z forward) to vehicle axes (x fwd, y left, z up)
T_VEHICLE_CAMERA = make_transform(
    np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.array([0.27, 0.0, 1.65])
)


class SimulationConfig(BaseModel):
    scene: Literal[
        "urban", "highway", "mixed", "interchange",  # street presets (`layout.py`)
        "receding", "approaching", "walkers", "market", "shadow", "parked_rows",  # situations
    ] = "urban"  # fmt: skip
    length: float = Field(60.0, gt=5.0, le=5000.0, description="metres of street driven")
    seed: int = Field(0, ge=0)
    scanner: Literal["hdl64", "profile"] = "hdl64"
    camera: bool = True
    pose_noise_m: float = Field(0.0, ge=0.0, description="GNSS/INS position noise (sigma)")
    pose_noise_deg: float = Field(0.0, ge=0.0, description="GNSS/INS heading noise (sigma)")
    write_map: bool | None = Field(None, description="write map.laz; default: profile only")
    compressed: bool = Field(False, description="scans as LAZ instead of KITTI .bin")
    drive_speed: float | None = Field(
        None,
        ge=2.0,
        le=30.0,
        description="the survey vehicle's speed (m/s); default: drawn from the seed (8-11 in "
        "town, 20-25 on a highway). Fixed, surveys of several lengths differ only in length",
    )
    vegetation: bool = Field(
        False,
        description="town streets: hedges and bushes in front of the buildings and on the "
        "verge, leaves a laser ray reaches into (the rest of the street stays the seed's)",
    )
    vary_scanner: bool = Field(
        False,
        description="hdl64: draw the rotating scanner from the seed (32 / 64 beams, azimuth "
        "step, mounting height, range noise, dropouts) instead of KITTI's HDL-64E",
    )


@dataclass
class SimulationSummary:
    out: Path
    frames: int
    points: int
    moving_objects: int
    parked_vehicles: int
    guardrails: list[str]
    seconds: float

    @property
    def points_per_second(self) -> float:
        return self.points / self.seconds if self.seconds > 0 else 0.0


def scanner_config(
    name: str, variant: np.random.Generator | None = None
) -> HDL64Config | ProfileConfig:
    """The named scanner; for hdl64 with a `variant` generator, a rotating scanner drawn from
    the range real ones span, so models trained on it do not learn one sensor's pattern."""
    if name != "hdl64":
        return ProfileConfig()
    if variant is None:
        return HDL64Config()
    beams = int(variant.choice([32, 64]))
    top, bottom = (10.67, -30.67) if beams == 32 else (2.0, -24.8)  # HDL-32E / HDL-64E fields
    return HDL64Config(
        beams=beams,
        elevation_max_deg=top,
        elevation_min_deg=bottom,
        azimuth_step_deg=round(float(variant.uniform(0.09, 0.35)), 3),
        mount_height=round(float(variant.uniform(1.6, 2.2)), 2),
        range_noise_m=round(float(variant.uniform(0.01, 0.04)), 3),
        dropout=round(float(variant.uniform(0.02, 0.15)), 3),
    )


def frame_pattern(config: HDL64Config | ProfileConfig, t_start: float):
    if isinstance(config, HDL64Config):
        return hdl64_pattern(config, t_start)
    return profile_pattern(config, t_start, t_start + 1.0 / FRAME_RATE)


def noisy_poses(poses: np.ndarray, config: SimulationConfig, rng) -> np.ndarray:
    """What a GNSS/INS with the configured noise would report for the true poses."""
    if config.pose_noise_m == 0 and config.pose_noise_deg == 0:
        return poses.copy()
    out = poses.copy()
    out[:, :3, 3] += rng.normal(0.0, config.pose_noise_m, (len(poses), 3))
    yaw = np.deg2rad(rng.normal(0.0, config.pose_noise_deg, len(poses)))
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.tile(np.eye(3), (len(poses), 1, 1))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = c, -s, s, c
    out[:, :3, :3] = Rz @ poses[:, :3, :3]
    return out


def scene_objects(scene: Scene) -> list[dict]:
    """The countable objects of the scene for scene.json, one entry per instance (a cyclist's
    bicycle and rider are one object with two classes)."""
    objects: dict[int, dict] = {}
    for b in scene.bodies:
        if b.instance == 0:
            continue
        entry = objects.setdefault(
            b.instance, {"instance": b.instance, "name": b.name, "semantic": [], "moving": b.moving}
        )
        entry["semantic"].append(int(b.semantic))
        if b.motion is not None:
            entry["mean_speed"] = round(float(np.mean(b.motion.speed(b.motion.times))), 3)
        if b.guardrail >= 0:
            entry["guardrail"] = b.guardrail
    return list(objects.values())


def count_vehicles(scene: Scene) -> tuple[int, int]:
    """(moving objects, parked vehicles) counted by instance."""
    vehicles = {Semantic.CAR, Semantic.OTHER_VEHICLE, Semantic.TRUCK, Semantic.BUS}
    moving = {b.instance for b in scene.bodies if b.moving and b.instance}
    parked = {b.instance for b in scene.bodies if not b.moving and b.semantic in vehicles}
    return len(moving), len(parked)


def _seeds(config: SimulationConfig) -> list[np.random.SeedSequence]:
    """Independent streams for the scene, the scanner, the GNSS/INS noise and the scanner's
    variant (`vary_scanner`); the first three are those of the seed before variants existed."""
    return np.random.SeedSequence(config.seed).spawn(4)


def rebuild_scene(config: SimulationConfig) -> Scene:
    """The exact scene a simulation with this config used (tests, evaluation)."""
    rng = np.random.default_rng(_seeds(config)[0])
    build = build_situation if config.scene in SITUATIONS else build_scene
    scene = build(config.scene, config.length, rng, config.drive_speed, config.vegetation)
    scene.seed = config.seed
    return scene


def simulate(
    config: SimulationConfig,
    out: Path,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> SimulationSummary:
    """Simulate and write the survey to OUT (built in OUT.partial, renamed when complete)."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise InputError(out, "already exists (pass --overwrite to replace it)")
    started = time.perf_counter()
    _, scan_seed, noise_seed, variant_seed = _seeds(config)
    scene = rebuild_scene(config)
    scan_rng = np.random.default_rng(scan_seed)
    caster = RayCaster(scene)
    table = BodyTable(scene)
    variant = np.random.default_rng(variant_seed) if config.vary_scanner else None
    scanner = scanner_config(config.scanner, variant)
    T_vs = scanner.T_vehicle_sensor
    T_cam_sensor = invert(T_VEHICLE_CAMERA) @ T_vs
    camera = CameraConfig()

    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        n_frames = int(np.floor(scene.duration * FRAME_RATE))
        starts = np.arange(n_frames) / FRAME_RATE
        refs = starts + 0.5 / FRAME_RATE
        T_world_vehicle = scene.vehicle_path.poses(refs)
        T_world_sensor = T_world_vehicle @ T_vs
        frames_world, frames_truth, frames_time = [], [], []
        for k in range(n_frames):
            points = scan(caster, frame_pattern(scanner, starts[k]), scene.vehicle_path, T_vs,
                          scanner, scan_rng)  # fmt: skip
            xyz_sensor = apply(invert(T_world_sensor[k]), points.xyz_world)
            kw.write_scan(partial, k, xyz_sensor, points.intensity, points.time, config.compressed)
            frames_world.append(points.xyz_world)
            frames_truth.append(table.truth(points.body, points.triangle, points.halo, points.time))
            frames_time.append(points.time)
            if config.camera:
                image = render(
                    caster, scene, T_world_vehicle[k] @ T_VEHICLE_CAMERA, refs[k], camera
                )
                kw.write_image(partial, k, image.rgb)
                kw.write_masks(partial, k, image.semantic, image.instance)
            if progress is not None:
                progress(k + 1, n_frames)

        sizes = [len(x) for x in frames_world]
        world = np.concatenate(frames_world) if frames_world else np.zeros((0, 3))
        semantic = np.concatenate([t.semantic for t in frames_truth])
        moving = np.concatenate([t.moving for t in frames_truth])
        pillar = pillar_classes(world, semantic, moving, scene.ground_height(world))
        for k, part in enumerate(np.split(pillar, np.cumsum(sizes)[:-1])):
            arrays = frames_truth[k].as_arrays() | {"pillar_class": part}
            if not config.compressed:  # LAZ scans carry the per-point time themselves
                arrays["time"] = frames_time[k]
            kw.write_point_truth(partial, k, arrays)

        # GNSS/INS trajectory at the scanner's rate (revolutions / profiles); frames take theirs
        rate = FRAME_RATE if isinstance(scanner, HDL64Config) else scanner.profiles_per_s
        traj_times = (
            refs if rate == FRAME_RATE else np.arange(round(n_frames * rate / FRAME_RATE)) / rate
        )
        traj_true = scene.vehicle_path.poses(traj_times) @ T_vs
        traj_measured = noisy_poses(traj_true, config, np.random.default_rng(noise_seed))
        kw.write_trajectory(partial / "trajectory.txt", traj_times, traj_measured)
        kw.write_trajectory(partial / "ground_truth" / "trajectory.txt", traj_times, traj_true)
        measured = (
            traj_measured[np.round(refs * rate).astype(int)]
            if rate != FRAME_RATE
            else traj_measured
        )
        kw.write_poses(partial / "poses.txt", measured)
        kw.write_poses(partial / "ground_truth" / "poses.txt", T_world_sensor)
        T_world_imu = measured @ invert(T_vs)
        speeds = scene.vehicle_path.speed(refs)
        kw.write_oxts(partial, kw.oxts_packets(T_world_imu, speeds), refs)
        if isinstance(scanner, HDL64Config):  # per-point time follows the azimuth
            kw.write_sweep_times(partial, refs, starts, starts + 1.0 / FRAME_RATE)
        else:
            (partial / "velodyne_points").mkdir(exist_ok=True)
            (partial / "velodyne_points" / "timestamps.txt").write_text(kw.format_timestamps(refs))
        if config.camera:
            (partial / "image_02" / "timestamps.txt").write_text(kw.format_timestamps(refs))
        kw.write_calibration(
            partial, camera.P, camera.width, camera.height, T_cam_sensor, invert(T_vs)
        )
        moving_count, parked = count_vehicles(scene)
        guardrail_kinds = [g["kind"] for g in scene.guardrails]
        kw.write_json(partial / "ground_truth" / "guardrails.json", scene.guardrails)
        kw.write_json(partial / "ground_truth" / "scene.json", {"objects": scene_objects(scene)})
        kw.write_json(
            partial / "ground_truth" / "simulation.json",
            {
                "name": f"sim-{config.scene}-{config.length:g}m-{config.scanner}-seed{config.seed}",
                "generator": f"mmsclean {__version__}",
                "config": config.model_dump(),
                "scanner": config.scanner,
                "scanner_params": asdict(scanner),
                "frame_rate_hz": FRAME_RATE,
                "frames": n_frames,
                "points": int(len(world)),
                "moving_objects": moving_count,
                "parked_vehicles": parked,
                "guardrails": guardrail_kinds,
                "pillar_cell_m": 0.2,
                "pillar_height_m": 3.0,
            },
        )
        write_map = (
            config.write_map if config.write_map is not None else config.scanner == "profile"
        )
        if write_map and len(world):
            write_accumulated_map(
                partial / "map.laz", world, frames_truth, pillar, sizes, frames_time
            )
        if out.exists():
            shutil.rmtree(out)
        partial.rename(out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return SimulationSummary(
        out=out,
        frames=n_frames,
        points=int(len(world)),
        moving_objects=moving_count,
        parked_vehicles=parked,
        guardrails=guardrail_kinds,
        seconds=time.perf_counter() - started,
    )


def write_accumulated_map(path, world, truths, pillar, sizes, times) -> None:
    """The MLS map: every point in world coordinates with its pillar class and source."""
    import datetime

    from app.io.asprs import (
        GUARDRAIL_ASPRS,
        REMOVED_CLUTTER_ASPRS,
        SEMANTICKITTI_TO_ASPRS,
        to_asprs,
    )
    from app.io.las import write_laz

    classification = to_asprs(np.concatenate([t.semantic for t in truths]), SEMANTICKITTI_TO_ASPRS)
    classification[np.concatenate([t.guardrail for t in truths]) >= 0] = GUARDRAIL_ASPRS
    classification[np.concatenate([t.moving for t in truths])] = REMOVED_CLUTTER_ASPRS
    frame = np.repeat(np.arange(len(sizes), dtype=np.uint32), sizes)
    index = np.concatenate([np.arange(n, dtype=np.uint32) for n in sizes])
    write_laz(
        path,
        world,
        mmsclean_label=pillar,
        classification=classification,
        source_frame=frame,
        source_index=index,
        gps_time=np.concatenate(times),
        creation_date=datetime.date(*kw.FIXED_DATE),
    )


def load_simulation_info(out: Path) -> dict:
    return json.loads((out / "ground_truth" / "simulation.json").read_text())
