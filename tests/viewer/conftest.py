"""Viewer fixtures: a migrated store with a small PLY map far from the world origin (unit
tests), and a real `mmsclean serve` with the sample survey and a known viser port."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.io import open_survey
from app.io.ply import write_ply
from app.store.db import dispose_engines, init_db, make_engine
from app.store.models import Survey
from app.store.surveys import register_opened_survey
from tests.api.server import ADMIN_PASSWORD, Server, free_port

WORLD_OFFSET = np.array([512_345.0, 5_401_234.0, 310.0])  # UTM-like: float32 would lose cm
OVERVIEW_POINTS = 50_000  # browser scenes stay small in the tests
TILE_POINTS = 40_000


def street_points(seed: int = 0) -> np.ndarray:
    """A 120 m x 30 m street (ground every 0.25 m, sloping 2 %) with a 4 m high box at x 20-22,
    in world coordinates far from the origin."""
    gx, gy = np.meshgrid(np.arange(0, 120, 0.25), np.arange(0, 30, 0.25), indexing="ij")
    ground = np.stack([gx.ravel(), gy.ravel(), 0.02 * gx.ravel()], axis=1)
    rng = np.random.default_rng(seed)
    box = rng.uniform([20, 10, 0.5], [22, 12, 4.5], size=(4000, 3))
    box[:, 2] += 0.02 * box[:, 0]
    return np.concatenate([ground, box]) + WORLD_OFFSET


@pytest.fixture
def engine(tmp_path: Path) -> Iterator[Engine]:
    engine = make_engine(f"sqlite:///{tmp_path / 'db' / 'mmsclean.sqlite3'}")
    init_db(engine)
    yield engine
    engine.dispose()
    dispose_engines()


@pytest.fixture
def ply_survey(tmp_path: Path, engine: Engine) -> Survey:
    """The street as a registered PLY survey (origin: its minimum corner in whole metres)."""
    path = write_ply(tmp_path / "street.ply", street_points())
    with Session(engine, expire_on_commit=False) as session:
        return register_opened_survey(
            session, open_survey(path, "ply"), format="ply", source_path=path.resolve()
        )


def login_token(server: Server, username: str = "admin", password: str = ADMIN_PASSWORD) -> str:
    response = httpx.post(
        f"{server.url}/auth/login", json={"username": username, "password": password}
    )
    response.raise_for_status()
    return response.json()["access_token"]


@pytest.fixture(scope="module")
def viewer_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A started server with the sample survey, viser on a known loopback port, small scenes."""
    data_dir = tmp_path_factory.mktemp("viewer-server") / "var"
    env = {
        "MMSCLEAN_VIEWER_PORT": str(free_port()),
        "MMSCLEAN_VIEWER_OVERVIEW_POINTS": str(OVERVIEW_POINTS),
        "MMSCLEAN_VIEWER_TILE_POINTS": str(TILE_POINTS),
        "MMSCLEAN_RETRAIN_EVERY": "0",
    }
    running = Server(data_dir, env=env).start()
    yield running
    running.stop()
