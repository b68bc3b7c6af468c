"""A small simulated street the pipeline tests share (synthetic)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from app.pipelines.phantom.model import save_model
from app.pipelines.phantom.network import PillarCNN
from app.simulate.survey import SimulationConfig, simulate


@pytest.fixture(scope="session")
def profile_street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """20 m of mixed street, profile scanner, no camera: phantoms, guardrails, full reference."""
    out = tmp_path_factory.mktemp("profile-street") / "sim"
    simulate(
        SimulationConfig(scene="mixed", length=20.0, seed=5, scanner="profile", camera=False), out
    )
    return out


@pytest.fixture(scope="session")
def random_phantom_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained (seeded) pillar CNN: contract tests need a model, not a good one."""
    torch.manual_seed(0)
    return save_model(tmp_path_factory.mktemp("model") / "net.pt", PillarCNN(), {"name": "random"})
