"""Settings from the environment; the error hierarchy's exit codes and HTTP statuses."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from app.core.errors import (
    ConfigError,
    ConflictError,
    InputError,
    MmscleanError,
    NotFoundError,
    UnknownFormatError,
)
from app.core.settings import Settings, get_settings


def test_database_defaults_to_sqlite_in_data_dir(isolated_data_dir: Path) -> None:
    settings = Settings()
    assert settings.data_dir == isolated_data_dir
    assert (
        settings.database_url == f"sqlite:///{(isolated_data_dir / 'mmsclean.sqlite3').resolve()}"
    )


def test_environment_prefix(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("MMSCLEAN_DATABASE_URL", "sqlite:///elsewhere.db")
    monkeypatch.setenv("MMSCLEAN_WEIGHTS_DIR", str(tmp_path / "w"))
    monkeypatch.setenv("MMSCLEAN_PORT", "8123")
    settings = Settings()
    assert settings.database_url == "sqlite:///elsewhere.db"
    assert settings.weights_dir == tmp_path / "w"
    assert settings.port == 8123


def test_bad_port_is_rejected(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MMSCLEAN_PORT", "70000")
    with pytest.raises(ValidationError, match="port"):
        Settings()
    get_settings.cache_clear()
    with pytest.raises(ConfigError, match="MMSCLEAN_PORT: .*70000"):
        get_settings()


def test_errors_carry_one_line_and_codes() -> None:
    err = InputError(Path("a/b.bin"), "truncated")
    assert str(err) == "a/b.bin: truncated" and err.http_status == 422 and err.exit_code != 0
    assert NotFoundError("x").http_status == 404
    assert ConflictError("x").http_status == 409
    for cls in (InputError, UnknownFormatError, NotFoundError, ConflictError):
        assert issubclass(cls, MmscleanError)
