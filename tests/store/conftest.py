"""Store fixtures: a migrated SQLite file database in tmp_path and a session on it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session

from app.store.db import dispose_engines, init_db, make_engine


@pytest.fixture(autouse=True)
def _dispose_shared_engines() -> Iterator[None]:
    yield
    dispose_engines()


@pytest.fixture
def db_path(tmp_path: Path) -> Path:
    return tmp_path / "db" / "mmsclean.sqlite3"


@pytest.fixture
def engine(db_path: Path) -> Iterator[Engine]:
    engine = make_engine(f"sqlite:///{db_path}")
    init_db(engine)
    yield engine
    engine.dispose()


@pytest.fixture
def session(engine: Engine) -> Iterator[Session]:
    with Session(engine) as session:
        yield session
