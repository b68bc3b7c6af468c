"""What every command group shares: the consoles, the `--format` and `--sensor` options, configs
built from options (a bad value named by its option), seed lists and the stage progress bar."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import typer
from rich.console import Console

from app.core.errors import ConfigError
from app.core.progress import Progress
from app.core.sensors import SensorKind, parse_sensor_kind

if TYPE_CHECKING:  # pydantic is imported by the commands that build a config
    from pydantic import BaseModel

console = Console()
err_console = Console(stderr=True)

FormatOption = Annotated[
    str, typer.Option("--format", "-f", help="kitti-raw, semantickitti, las, ply, pcd, sim")
]

SensorOption = Annotated[
    str | None,
    typer.Option(
        "--sensor",
        help="rotating or profile: the scanner kind, where the survey does not tell it "
        "(mmsclean info shows what it tells)",
    ),
]

Config = TypeVar("Config", bound="BaseModel")


def sensor_kind(value: str | None) -> SensorKind | None:
    """The `--sensor` option as a SensorKind (None when not given); ConfigError otherwise."""
    if value is None:
        return None
    try:
        return parse_sensor_kind(value, allow_unknown=False)
    except ValueError as exc:
        raise ConfigError("--sensor", str(exc)) from None


def config_from_options(
    model: type[Config], renames: dict[str, str] | None = None, **values: Any
) -> Config:
    """`model(**values)`; its first validation problem is a `ConfigError` named by the
    command-line option (`field_name` -> `--field-name`, or as `renames` says) and the value."""
    from pydantic import ValidationError

    try:
        return model(**values)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = str(first["loc"][0])
        option = (renames or {}).get(field, field).replace("_", "-")
        raise ConfigError(f"--{option}", f"{first['msg']} (got {first.get('input')!r})") from None


def seed_list(option: str, text: str) -> list[int]:
    """ "101,102" or "101-110" (or both, comma separated) -> the seeds."""
    try:
        seeds = []
        for part in filter(None, (p.strip() for p in text.split(","))):
            first, _, last = part.partition("-")
            seeds += list(range(int(first), int(last or first) + 1))
    except ValueError:
        raise ConfigError(option, f"not a list of integers: {text!r}") from None
    return seeds


@contextmanager
def stage_progress(name: str) -> Iterator[Progress]:
    """A transient bar on stderr named `name`; yields the pipelines' `progress(stage, fraction)`
    callback, which moves the bar and shows the stage."""
    from rich.progress import Progress as Bar

    with Bar(console=err_console, transient=True) as bar:
        task = bar.add_task(name, total=1.0)
        yield lambda stage, f: bar.update(task, completed=f, description=stage)
