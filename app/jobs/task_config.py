"""Checking a job's config: one-line errors naming `config.<field>`, and the model a job runs.

Nothing in a job config names a file to load: a job names a model by its registry id
(`config.model_id`, a row of `GET /models` of the job's pipeline) and runs the promoted model
without one. A checkpoint path from a request would let anyone who can upload a file make the
server unpickle it.
"""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError
from sqlmodel import Session

from app.core.errors import ConfigError
from app.store.models import ModelVersion, Pipeline

Config = TypeVar("Config", bound=BaseModel)

MODEL_PATH_REFUSED = (
    "jobs name a model by its registry id (config.model_id, see GET /models); "
    "file paths are not accepted"
)


def refuse_model_path(values: dict[str, Any] | None) -> None:
    """A config naming a checkpoint file (`model_path`) is refused, whatever the kind."""
    if isinstance(values, dict) and "model_path" in values:
        raise ConfigError("config.model_path", MODEL_PATH_REFUSED)


def validated(
    model: type[Config], values: dict[str, Any] | None, known: tuple[str, ...] | None = None
) -> Config:
    """`model` from a job's config dict; the first problem as ConfigError('config.<field>').
    With `known`, a key outside it is refused first, naming the fields a job may set."""
    refuse_model_path(values)
    if known is not None:
        unknown = sorted(set(values or {}) - set(known))
        if unknown:
            raise ConfigError(f"config.{unknown[0]}", f"unknown field; known: {', '.join(known)}")
    try:
        return model.model_validate(dict(values or {}))
    except ValidationError as exc:
        raise config_error(exc) from None


def config_error(exc: ValidationError) -> ConfigError:
    """The first problem of a config's ValidationError, named `config.<field>`, with the value."""
    first = exc.errors()[0]
    field = ".".join(str(p) for p in first["loc"]) or "config"
    given = ""
    if "input" in first and first["loc"]:
        value = repr(first["input"])
        given = f" (got {value if len(value) <= 80 else value[:77] + '...'})"
    return ConfigError(f"config.{field}", f"{first['msg']}{given}")


def job_model(session: Session, pipeline: Pipeline, model_id: int) -> ModelVersion:
    """The registry row `model_id` names; ConfigError('config.model_id') when there is none or
    it belongs to another pipeline."""
    version = session.get(ModelVersion, model_id)
    if version is None:
        raise ConfigError("config.model_id", f"no model version {model_id} (see GET /models)")
    if version.pipeline != pipeline:
        raise ConfigError(
            "config.model_id",
            f"model version {model_id} is a {version.pipeline.value} model, "
            f"not a {pipeline.value} one",
        )
    return version
