"""API fixtures: one real server per module (no sample survey unless a test asks for it)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.server import Server


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A started server with an empty database (only the user `admin`)."""
    data_dir: Path = tmp_path_factory.mktemp("server") / "var"
    running = Server(data_dir, env={"MMSCLEAN_SAMPLE_DIR": ""}).start()
    yield running
    running.stop()


@pytest.fixture(scope="module")
def sample_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A started server that loaded the sample survey on its first start."""
    data_dir: Path = tmp_path_factory.mktemp("sample-server") / "var"
    running = Server(data_dir).start()
    yield running
    running.stop()
