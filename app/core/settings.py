"""Process-wide settings, read from the environment (prefix `MMSCLEAN_`) and `.env`."""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from app.core.errors import ConfigError


def half_physical_memory_mb() -> int:
    """Half the machine's physical memory in MB (the default job memory limit)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not a POSIX system: assume 8 GB
        total = 8 * 1024**3
    return max(64, total // (2 * 1024**2))


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="MMSCLEAN_", env_file=".env", extra="ignore")

    data_dir: Path = Field(Path("var"), description="database, caches, imported surveys, exports")
    database_url: str = Field("", description="SQLAlchemy URL; empty = SQLite file in data_dir")
    weights_dir: Path = Field(Path("models"), description="pretrained image-model weights")
    real_data: Path | None = Field(None, description="real KITTI/SemanticKITTI sample (tests)")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535, description="web app (API, dashboard, viewer)")
    viewer_port: int = Field(0, ge=0, le=65535, description="loopback viser port; 0 = free port")
    viewer_overview_points: int = Field(
        500_000, ge=1000, description="most points of the viewer's downsampled map overview"
    )
    viewer_tile_points: int = Field(
        1_000_000, ge=1000, description="most points of the full-resolution tile in focus"
    )
    viewer_log_slower_ms: float = Field(
        200, ge=0, le=60_000,
        description="log each viewer interaction the server answers slower than this (0: all)",
    )  # fmt: skip
    viewer_session_check_s: float = Field(
        10, ge=0.1, le=300, description="how often an open viewer checks its login is live"
    )
    admin_password: str | None = None
    login_free_failures: int = Field(
        5, ge=1, le=1000, description="failed logins for one user name before lock-outs"
    )
    login_address_free_failures: int = Field(
        20, ge=1, le=10_000, description="failed logins from one client address before lock-outs"
    )
    login_window_s: float = Field(
        900, ge=1, le=86_400, description="a quiet time this long forgets the failed logins"
    )
    login_first_delay_s: float = Field(
        1.0, gt=0, le=3600, description="the first lock-out; each further failure doubles it"
    )
    login_max_delay_s: float = Field(
        900, gt=0, le=86_400, description="the longest lock-out after failed logins"
    )
    import_root: Path | None = Field(
        None, description="surveys may be imported from paths inside it; empty = data_dir"
    )
    max_upload_mb: float = Field(4096, gt=0, description="largest survey upload accepted")
    min_free_mb: float = Field(
        500, ge=0, description="less free space on the data dir's disk: writes answer 507"
    )
    workers: int = Field(2, ge=1, le=64, description="job worker processes")
    job_memory_mb: int = Field(
        default_factory=half_physical_memory_mb,
        ge=64,
        description="a job whose estimated memory is larger is refused when queued; "
        "default: half the machine's physical memory",
    )
    dask_scheduler: str | None = Field(
        None,
        pattern=r"^(tcp|tls)://[A-Za-z0-9.\-\[\]:]+:[0-9]{1,5}$",
        description="address of an existing Dask scheduler (tcp://host:8786) that runs the "
        "tiles; empty = a local cluster of `workers` processes started on demand",
    )
    tile_worker_memory_mb: int = Field(
        2048, ge=256, le=1_048_576, description="memory limit of each local tile worker"
    )
    retrain_every: int = Field(
        2000, ge=0, description="newly reviewed pillar labels that queue retraining; 0 = off"
    )
    sample_dir: Path | None = Field(
        Path(__file__).resolve().parents[2] / "data_samples" / "urban-60m",
        description="survey loaded into an empty database on first start; empty = none",
    )

    @field_validator("sample_dir", "dask_scheduler", mode="before")
    @classmethod
    def _empty_means_none(cls, value: object) -> object:
        return None if value == "" else value

    @model_validator(mode="after")
    def _default_database(self) -> Settings:
        if not self.database_url:
            self.database_url = f"sqlite:///{(self.data_dir / 'mmsclean.sqlite3').resolve()}"
        return self

    @property
    def cache_dir(self) -> Path:
        return self.data_dir / "cache"

    @property
    def jobs_dir(self) -> Path:
        """One folder per job: its log and its outputs."""
        return self.data_dir / "jobs"

    @property
    def surveys_dir(self) -> Path:
        """Uploaded surveys, one folder each."""
        return self.data_dir / "surveys"

    @property
    def allowed_import_root(self) -> Path:
        return (self.import_root or self.data_dir).resolve()


@lru_cache
def get_settings() -> Settings:
    """The settings; an invalid environment variable is a one-line ConfigError naming it."""
    try:
        return Settings()
    except ValidationError as exc:
        first = exc.errors()[0]
        field = "MMSCLEAN_" + str(first["loc"][0]).upper() if first["loc"] else "settings"
        raise ConfigError(field, f"{first['msg']} (got {first.get('input')!r})") from None
