"""Engine settings, the shared engine cache and the session helpers."""

from __future__ import annotations

import logging
import stat
from pathlib import Path

import pytest
from sqlalchemy.engine import Engine
from sqlmodel import Session, select

from app.core.errors import ConflictError
from app.core.settings import get_settings
from app.store.db import (
    commit,
    get_engine,
    get_session,
    init_db,
    make_engine,
    secure_dir,
    session_scope,
)
from app.store.migrations import SCHEMA_VERSION
from app.store.models import LabelSource, PillarLabel, Survey, User


def _pragma(engine: Engine, name: str) -> object:
    with engine.connect() as conn:
        return conn.exec_driver_sql(f"PRAGMA {name}").scalar()


def test_sqlite_file_runs_in_wal_mode_with_foreign_keys(engine: Engine, db_path: Path) -> None:
    assert db_path.is_file()
    assert _pragma(engine, "journal_mode") == "wal"
    assert _pragma(engine, "foreign_keys") == 1
    assert _pragma(engine, "synchronous") == 1  # NORMAL
    assert _pragma(engine, "busy_timeout") == 30000


def test_make_engine_creates_the_folder_but_not_the_database(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "x.sqlite3"
    engine = make_engine(f"sqlite:///{path}")
    assert path.parent.is_dir() and not path.exists()
    engine.dispose()


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_database_files_are_owner_only_from_the_start(tmp_path: Path) -> None:
    """Password hashes live in the file: it, its -wal / -shm and a folder made for it are
    never readable by others, whatever the umask."""
    path = tmp_path / "new" / "mmsclean.sqlite3"
    engine = make_engine(f"sqlite:///{path}")
    assert _mode(path.parent) == 0o700
    init_db(engine)
    with Session(engine) as session:
        session.add(User(username="ann", hashed_password="x"))
        session.commit()
        files = {p.name: _mode(p) for p in path.parent.iterdir()}
    assert files == {
        "mmsclean.sqlite3": 0o600,
        "mmsclean.sqlite3-wal": 0o600,
        "mmsclean.sqlite3-shm": 0o600,
    }
    engine.dispose()


def test_an_existing_database_open_to_others_is_tightened_and_logged(
    engine: Engine, db_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with Session(engine) as session:
        session.add(User(username="ann", hashed_password="x"))
        session.commit()
    files = [p for p in db_path.parent.iterdir() if p.name.startswith(db_path.name)]
    assert len(files) == 3  # the database, -wal, -shm
    for file in files:
        file.chmod(0o644)
    engine.dispose()
    with caplog.at_level(logging.WARNING, logger="app.store.db"):
        reopened = make_engine(f"sqlite:///{db_path}")
        with Session(reopened) as session:
            assert session.exec(select(User.username)).all() == ["ann"]
    assert {f.name: _mode(f) for f in files} == {f.name: 0o600 for f in files}
    assert f"{db_path} was open to others (mode 0644); now 0600" in caplog.messages
    reopened.dispose()


def test_secure_dir_makes_or_tightens_a_folder(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    made = secure_dir(tmp_path / "a" / "var")
    assert _mode(made) == 0o700
    loose = tmp_path / "loose"
    loose.mkdir(mode=0o755)
    loose.chmod(0o755)
    with caplog.at_level(logging.WARNING, logger="app.store.db"):
        secure_dir(loose)
    assert _mode(loose) == 0o700
    assert f"{loose} was open to others (mode 0755); now 0700" in caplog.messages


def test_get_engine_defaults_to_the_data_dir_and_is_cached(isolated_data_dir: Path) -> None:
    engine = get_engine()
    assert engine is get_engine()
    assert engine is get_engine(get_settings().database_url)
    assert Path(engine.url.database) == (isolated_data_dir / "mmsclean.sqlite3").resolve()
    assert _pragma(engine, "user_version") == SCHEMA_VERSION  # migrated on first use
    with Session(engine) as session:
        assert session.exec(select(User)).all() == []


def test_get_engine_caches_per_url(tmp_path: Path) -> None:
    a = get_engine(f"sqlite:///{tmp_path / 'a.sqlite3'}")
    b = get_engine(f"sqlite:///{tmp_path / 'b.sqlite3'}")
    assert a is not b
    assert a is get_engine(f"sqlite:///{tmp_path / 'a.sqlite3'}")


def test_session_scope_commits_on_success_and_rolls_back_on_error(engine: Engine) -> None:
    with session_scope(engine) as session:
        session.add(User(username="ann", hashed_password="x"))
    with pytest.raises(RuntimeError), session_scope(engine) as session:
        session.add(User(username="bob", hashed_password="x"))
        session.flush()
        raise RuntimeError("boom")
    with session_scope(engine) as session:
        names = session.exec(select(User.username)).all()
    assert names == ["ann"]


def test_session_scope_objects_stay_readable_after_the_block(engine: Engine) -> None:
    with session_scope(engine) as session:
        user = User(username="ann", hashed_password="x")
        session.add(user)
    assert user.id is not None and user.username == "ann" and user.version == 1


def test_duplicate_in_session_scope_is_a_conflict(engine: Engine) -> None:
    with session_scope(engine) as session:
        session.add(User(username="ann", hashed_password="x"))
    duplicate = "user with the same username already exists"
    with pytest.raises(ConflictError, match=duplicate), session_scope(engine) as session:
        session.add(User(username="ann", hashed_password="y"))


def test_concurrent_edit_of_the_same_version_loses_with_a_conflict(engine: Engine) -> None:
    with session_scope(engine) as session:
        survey = Survey(name="s", format="sim", source_path="/x")
        session.add(survey)
        session.flush()
        session.add(PillarLabel(survey_id=survey.id, cell_id=7, label=0, source=LabelSource.human))
    with Session(engine) as first, Session(engine) as second:
        mine = first.exec(select(PillarLabel)).one()
        theirs = second.exec(select(PillarLabel)).one()
        assert mine.version == theirs.version == 1
        mine.label = 3
        commit(first)
        assert mine.version == 2
        theirs.label = 1
        with pytest.raises(ConflictError, match="pillar_label was changed by someone else"):
            commit(second)
    with Session(engine) as session:
        stored = session.exec(select(PillarLabel)).one()
        assert (stored.label, stored.version) == (3, 2)


def test_stale_write_in_session_scope_is_a_conflict(engine: Engine) -> None:
    with session_scope(engine) as session:
        user = User(username="ann", hashed_password="x")
        session.add(user)
    with pytest.raises(ConflictError), session_scope(engine) as session:
        stale = session.get(User, user.id)
        with session_scope(engine) as other:
            other.get(User, user.id).is_active = False
        stale.role = "admin"


def test_get_session_yields_a_session_on_the_shared_engine() -> None:
    dependency = get_session()
    session = next(dependency)
    assert session.get_bind() is get_engine()
    session.add(User(username="ann", hashed_password="x"))
    session.commit()
    dependency.close()
    with session_scope() as check:
        assert check.exec(select(User.username)).all() == ["ann"]


def test_get_session_turns_a_duplicate_raised_in_the_route_into_a_conflict() -> None:
    with session_scope() as session:
        session.add(User(username="ann", hashed_password="x"))
    dependency = get_session()
    session = next(dependency)
    session.add(User(username="ann", hashed_password="y"))
    try:
        session.commit()
    except Exception as exc:  # what FastAPI does with a route's exception
        with pytest.raises(ConflictError):
            dependency.throw(exc)
    else:
        pytest.fail("duplicate username was accepted")
