"""Sensor kind from the reader or from a map's point times (app.io.sensor_kind)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.core.sensors import SensorKind
from app.io.las import read_las, write_laz
from app.io.ply import read_ply, write_ply
from app.io.registry import open_survey
from app.io.sensor_kind import detect_from_times, detect_sensor_kind
from app.simulate.survey import SimulationConfig, simulate


@pytest.fixture(scope="module")
def sim_maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("sensor-kind")
    maps = {}
    for scanner, length in (("profile", 12.0), ("hdl64", 6.0)):
        config = SimulationConfig(
            scene="urban", length=length, seed=3, scanner=scanner, camera=False, write_map=True
        )
        maps[scanner] = simulate(config, out / scanner).out / "map.laz"
    return maps


@pytest.mark.parametrize(("scanner", "kind"), [("profile", "profile"), ("hdl64", "rotating")])
def test_a_map_tells_its_scanner_by_its_revisit_period(
    sim_maps: dict[str, Path], scanner: str, kind: str
) -> None:
    detection = detect_sensor_kind(read_las(sim_maps[scanner]))
    assert detection.kind == SensorKind(kind), detection.reason
    assert "revisit period" in detection.reason


def test_readers_of_sensor_formats_name_their_scanner(sim_maps: dict[str, Path]) -> None:
    assert detect_sensor_kind(open_survey(sim_maps["hdl64"].parent, "sim")).kind == "rotating"
    assert detect_sensor_kind(open_survey(sim_maps["profile"].parent, "sim")).kind == "profile"


def test_a_real_rotating_map_with_frame_times_is_rotating(real_data: Path, tmp_path: Path) -> None:
    """SemanticKITTI 05 accumulated into one LAS, each point stamped with its frame's time (as a
    tool that writes maps from a KITTI drive does): the 0.1 s revolution shows."""
    survey = open_survey(real_data / "semantickitti" / "sequences" / "05", "semantickitti")
    xyz, times = [], []
    for frame in survey.frames:
        points = frame.world_points().xyz
        xyz.append(points)
        times.append(np.full(len(points), frame.timestamp))
    path = tmp_path / "seq05.laz"
    write_laz(path, np.concatenate(xyz), gps_time=np.concatenate(times))
    detection = detect_sensor_kind(read_las(path))
    assert detection.kind == SensorKind.ROTATING, detection.reason


def test_without_times_the_kind_is_unknown(sim_maps: dict[str, Path], tmp_path: Path) -> None:
    cloud = read_las(sim_maps["profile"]).frames[0].points()
    no_time = tmp_path / "no_time.laz"
    write_laz(no_time, cloud.xyz)  # gps_time all zero
    assert detect_sensor_kind(read_las(no_time)).kind == SensorKind.UNKNOWN
    ply = tmp_path / "map.ply"
    write_ply(ply, cloud.xyz[:50_000])
    detection = detect_sensor_kind(read_ply(ply))
    assert detection.kind == SensorKind.UNKNOWN
    assert "no time" in detection.reason


def test_random_times_are_neither_kind() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 5, (200_000, 3))
    time = rng.uniform(0, 1000, len(xyz))  # revisits seconds apart
    assert detect_from_times(xyz, time).kind == SensorKind.UNKNOWN
