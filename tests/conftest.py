"""Shared fixtures: the real-data folder, a temporary data dir per test."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def real_data() -> Path:
    """The real KITTI / SemanticKITTI sample named by MMSCLEAN_REAL_DATA; skip when unset."""
    value = os.environ.get("MMSCLEAN_REAL_DATA")
    if not value:
        pytest.skip("MMSCLEAN_REAL_DATA is not set (real KITTI/SemanticKITTI sample)")
    path = Path(value).resolve()
    if not path.is_dir():
        pytest.skip(f"MMSCLEAN_REAL_DATA={value} is not a folder")
    return path


@pytest.fixture(autouse=True)
def isolated_data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Each test gets its own MMSCLEAN_DATA_DIR so caches and databases never leak between tests."""
    data_dir = tmp_path / "mmsclean-data"
    monkeypatch.setenv("MMSCLEAN_DATA_DIR", str(data_dir))
    monkeypatch.delenv("MMSCLEAN_DATABASE_URL", raising=False)
    from app.core.settings import get_settings

    get_settings.cache_clear()
    yield data_dir
    get_settings.cache_clear()
