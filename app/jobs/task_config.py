"""Checking a job's config: one-line errors naming `config.<field>`, and model checkpoints a
job may load (inside the repository's models/ or the data directory only: a job must not load
arbitrary files of the server)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from app.core.errors import ConfigError
from app.core.settings import Settings

MODELS_DIR = Path(__file__).resolve().parents[2] / "models"

Config = TypeVar("Config", bound=BaseModel)


def validated(model: type[Config], values: dict[str, Any] | None) -> Config:
    """`model` from a job's config dict; the first problem as ConfigError('config.<field>')."""
    try:
        return model.model_validate(dict(values or {}))
    except ValidationError as exc:
        first = exc.errors()[0]
        field = ".".join(str(p) for p in first["loc"]) or "config"
        raise ConfigError(f"config.{field}", first["msg"]) from None


def allowed_model_path(value: object, settings: Settings) -> Path | None:
    """A checkpoint path inside models/ or the data directory (relative paths are taken from
    the repository root, e.g. models/phantom/x.pt); None stays None (the promoted model)."""
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        raise ConfigError("config.model_path", "must be a non-empty path")
    path = Path(value)
    path = (path if path.is_absolute() else MODELS_DIR.parent / path).resolve()
    roots = (MODELS_DIR.resolve(), settings.data_dir.resolve())
    if not any(path.is_relative_to(root) for root in roots):
        where = " or ".join(str(r) for r in roots)
        raise ConfigError("config.model_path", f"{value} is outside {where}")
    if not path.is_file():
        raise ConfigError("config.model_path", f"{path} does not exist")
    return path
