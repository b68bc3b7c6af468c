"""docker-compose.yml and Dockerfile are consistent (no Docker engine runs here to build them)."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import yaml

from app.cli import cli

ROOT = Path(__file__).resolve().parents[1]


def dockerfile_instruction(name: str) -> str:
    text = (ROOT / "Dockerfile").read_text()
    matches = re.findall(rf"^{name}\s+(.+)$", text, flags=re.MULTILINE)
    assert matches, f"Dockerfile has no {name}"
    return matches[-1]


def test_compose_service_ports_and_volume() -> None:
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    app = compose["services"]["app"]
    assert app["build"]["context"] == "."
    assert (ROOT / app["build"]["dockerfile"]).is_file()
    assert "8000:8000" in app["ports"]
    data_dir = app["environment"]["MMSCLEAN_DATA_DIR"]
    named = [v for v in app["volumes"] if v.split(":")[0] in compose["volumes"]]
    assert any(v.split(":")[1] == data_dir for v in named), "data dir is not on a named volume"


def test_dockerfile_command_exists() -> None:
    command = json.loads(dockerfile_instruction("CMD"))
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert command[0] in pyproject["project"]["scripts"]
    assert pyproject["project"]["scripts"][command[0]] == "app.cli:main"
    registered = {c.name or c.callback.__name__ for c in cli.registered_commands}
    assert command[1] in registered
    assert command[command.index("--port") + 1] == "8000"
    assert "8000" in dockerfile_instruction("EXPOSE")
    assert "/data" in dockerfile_instruction("VOLUME")
    for path in re.findall(r"^COPY\s+(\S+)", (ROOT / "Dockerfile").read_text(), flags=re.MULTILINE):
        assert (ROOT / path).exists(), f"Dockerfile copies {path}, which is not in the repository"


def test_compose_runs_tiles_on_a_scheduler_and_scalable_workers() -> None:
    """The app sends tiles to the scheduler service; every service of the image mounts the data
    volume where the app keeps it (workers read surveys and write tiles there); the worker
    service has no fixed name or port, so `--scale worker=N` works; the dashboard is published
    on the host's loopback only."""
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert services["app"]["environment"]["MMSCLEAN_DASK_SCHEDULER"] == "tcp://scheduler:8786"
    scheduler, worker = services["scheduler"], services["worker"]
    assert scheduler["command"][:2] == ["dask", "scheduler"] and "8786" in scheduler["command"]
    assert worker["command"][:3] == ["dask", "worker", "tcp://scheduler:8786"]
    assert "container_name" not in worker and "ports" not in worker
    assert all(p.startswith("127.0.0.1:") for p in scheduler["ports"])
    data_dir = services["app"]["environment"]["MMSCLEAN_DATA_DIR"]
    for name in ("app", "scheduler", "worker"):
        assert services[name]["environment"]["MMSCLEAN_DATA_DIR"] == data_dir
        assert any(
            v.split(":")[:2] == ["mmsclean-data", data_dir] for v in services[name]["volumes"]
        )
        assert services[name]["image"] == services["app"]["image"]
