"""Rotating-scanner variants of the simulator (`vary_scanner`): drawn from the seed, recorded."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from app.simulate.scanners import HDL64Config, ProfileConfig
from app.simulate.survey import SimulationConfig, scanner_config, simulate


def test_variants_span_real_rotating_scanners_and_are_deterministic() -> None:
    draws = [scanner_config("hdl64", np.random.default_rng(seed)) for seed in range(40)]
    assert {d.beams for d in draws} == {32, 64}
    assert all(0.09 <= d.azimuth_step_deg <= 0.35 for d in draws)
    assert all(1.6 <= d.mount_height <= 2.2 and 0.02 <= d.dropout <= 0.15 for d in draws)
    assert scanner_config("hdl64", np.random.default_rng(3)) == draws[3]
    assert scanner_config("hdl64") == HDL64Config()  # no variant: KITTI's HDL-64E
    assert scanner_config("profile", np.random.default_rng(0)) == ProfileConfig()


def test_a_varied_drive_records_its_scanner(tmp_path: Path) -> None:
    config = SimulationConfig(
        scene="urban", length=6.0, seed=601, scanner="hdl64", camera=False, vary_scanner=True
    )
    simulate(config, tmp_path / "drive")
    info = json.loads((tmp_path / "drive" / "ground_truth" / "simulation.json").read_text())
    _, _, _, variant = np.random.SeedSequence(601).spawn(4)
    expected = scanner_config("hdl64", np.random.default_rng(variant))
    assert info["scanner_params"]["beams"] == expected.beams
    assert info["scanner_params"]["azimuth_step_deg"] == expected.azimuth_step_deg
