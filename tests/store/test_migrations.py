"""Schema versions: new databases are stamped, old ones upgraded in place, newer ones refused."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine
from sqlmodel import Session, select

from app.core.errors import MmscleanError
from app.store import migrations
from app.store.db import get_engine, init_db, make_engine
from app.store.migrations import (
    MIGRATIONS,
    SCHEMA_VERSION,
    SchemaVersionError,
    StoreError,
    add_column,
    has_column,
    migrate,
)
from app.store.models import LabelSource, PillarLabel, Survey


def _user_version(engine: Engine) -> int:
    with engine.connect() as conn:
        return conn.exec_driver_sql("PRAGMA user_version").scalar()


def _tables(engine: Engine) -> set[str]:
    return set(sa.inspect(engine).get_table_names())


def _fill(engine: Engine) -> None:
    with Session(engine) as session:
        survey = Survey(name="old", format="sim", source_path="/s")
        session.add(survey)
        session.flush()
        session.add_all(
            PillarLabel(survey_id=survey.id, cell_id=c, label=c % 4, source=LabelSource.human)
            for c in range(5)
        )
        session.commit()


def _to_v2(conn: Connection) -> None:
    add_column(conn, "pillar_label", "note TEXT NOT NULL DEFAULT ''")


def test_every_version_has_its_migration() -> None:
    assert SCHEMA_VERSION >= 1
    assert set(MIGRATIONS) == set(range(2, SCHEMA_VERSION + 1))


def test_new_database_gets_all_tables_and_the_current_version(engine: Engine) -> None:
    assert _user_version(engine) == SCHEMA_VERSION
    assert {"user", "survey", "frame", "job", "pillar_label", "clutter_instance",
            "clutter_decision", "guardrail_slice", "guardrail_model", "model_version",
            "audit_event"} <= _tables(engine)  # fmt: skip


def test_migrating_a_current_database_changes_nothing(engine: Engine, db_path: Path) -> None:
    _fill(engine)
    assert migrate(engine) == SCHEMA_VERSION
    assert not list(db_path.parent.glob("*.bak"))
    with Session(engine) as session:
        assert len(session.exec(select(PillarLabel)).all()) == 5


def test_old_database_is_migrated_keeping_its_rows(
    engine: Engine, db_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _fill(engine)
    engine.dispose()
    assert _user_version(engine) == 1
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 2)
    monkeypatch.setitem(MIGRATIONS, 2, _to_v2)

    reopened = make_engine(f"sqlite:///{db_path}")
    assert init_db(reopened) == 2

    assert _user_version(reopened) == 2
    with reopened.connect() as conn:
        assert has_column(conn, "pillar_label", "note")
        rows = conn.exec_driver_sql("SELECT cell_id, label, note FROM pillar_label ORDER BY 1")
        assert rows.all() == [(c, c % 4, "") for c in range(5)]
        assert conn.exec_driver_sql("PRAGMA foreign_key_check").all() == []
    # the version 1 file was copied aside first, complete
    backup = db_path.with_name(db_path.name + ".schema-v1.bak")
    copy = make_engine(f"sqlite:///{backup}")
    assert _user_version(copy) == 1
    with copy.connect() as conn:
        assert not has_column(conn, "pillar_label", "note")
        assert conn.exec_driver_sql("SELECT count(*) FROM pillar_label").scalar() == 5
    copy.dispose()
    # and a second start finds nothing to do
    assert migrate(reopened) == 2
    assert len(list(db_path.parent.glob("*.bak"))) == 1
    reopened.dispose()


def test_migrations_run_in_order_from_the_stored_version(
    engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    ran: list[int] = []
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 4)
    for version in (4, 2, 3):
        monkeypatch.setitem(MIGRATIONS, version, lambda conn, v=version: ran.append(v))
    assert migrate(engine) == 4
    assert ran == [2, 3, 4]
    assert _user_version(engine) == 4


def test_failing_migration_leaves_the_database_as_it_was(
    engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    _fill(engine)

    def broken(conn: Connection) -> None:
        _to_v2(conn)
        conn.exec_driver_sql("UPDATE pillar_label SET note = 'half-done'")
        raise RuntimeError("migration bug")

    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 2)
    monkeypatch.setitem(MIGRATIONS, 2, broken)
    with pytest.raises(RuntimeError, match="migration bug"):
        migrate(engine)
    assert _user_version(engine) == 1
    with engine.connect() as conn:
        assert not has_column(conn, "pillar_label", "note")
        assert conn.exec_driver_sql("SELECT count(*) FROM pillar_label").scalar() == 5


def test_missing_migration_is_a_programming_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 3)
    monkeypatch.setitem(MIGRATIONS, 2, _to_v2)
    with pytest.raises(RuntimeError, match=r"no migration to schema version\(s\) \[3\]"):
        migrate(make_engine("sqlite://"))


def test_database_from_a_newer_mmsclean_is_refused(engine: Engine, db_path: Path) -> None:
    _fill(engine)
    with engine.begin() as conn:
        conn.exec_driver_sql("PRAGMA user_version = 7")
    engine.dispose()
    reopened = make_engine(f"sqlite:///{db_path}")
    with pytest.raises(SchemaVersionError) as caught:
        init_db(reopened)
    message = str(caught.value)
    assert message == (
        f"database {db_path} has schema version 7, this mmsclean knows up to "
        f"{SCHEMA_VERSION}; upgrade mmsclean"
    )
    assert "\n" not in message and isinstance(caught.value, MmscleanError)
    assert caught.value.exit_code != 0
    assert _user_version(reopened) == 7  # untouched
    reopened.dispose()


def test_newer_empty_database_is_refused_before_creating_tables(db_path: Path) -> None:
    engine = make_engine(f"sqlite:///{db_path}")
    with engine.begin() as conn:
        conn.exec_driver_sql("PRAGMA user_version = 2")
    with pytest.raises(SchemaVersionError, match="schema version 2"):
        get_engine(f"sqlite:///{db_path}")
    assert _tables(engine) == set()
    engine.dispose()


def test_a_file_that_is_not_a_database_gives_one_clear_line(tmp_path: Path) -> None:
    path = tmp_path / "notes.sqlite3"
    path.write_bytes(b"these are not the pages you are looking for\n" * 200)
    with pytest.raises(StoreError) as caught:
        init_db(make_engine(f"sqlite:///{path}"))
    assert str(caught.value) == f"database {path}: cannot open (file is not a database)"


def test_version_table_is_used_where_there_is_no_user_version(
    db_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(migrations, "_uses_pragma", lambda conn: False)
    engine = make_engine(f"sqlite:///{db_path}")
    assert migrate(engine) == SCHEMA_VERSION
    assert migrate(engine) == SCHEMA_VERSION
    with engine.connect() as conn:
        assert conn.exec_driver_sql("SELECT version FROM schema_version").all() == [(1,)]
        assert conn.exec_driver_sql("PRAGMA user_version").scalar() == 0
    assert "pillar_label" in _tables(engine)

    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 2)
    monkeypatch.setitem(MIGRATIONS, 2, _to_v2)
    assert migrate(engine) == 2
    with engine.connect() as conn:
        assert conn.exec_driver_sql("SELECT version FROM schema_version").all() == [(2,)]
        assert has_column(conn, "pillar_label", "note")

    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 1)
    with pytest.raises(
        SchemaVersionError, match="has schema version 2, this mmsclean knows up to 1"
    ):
        migrate(engine)
    engine.dispose()


def test_concurrent_first_starts_create_the_database_once(db_path: Path) -> None:
    engines = [make_engine(f"sqlite:///{db_path}") for _ in range(4)]
    barrier = threading.Barrier(len(engines))
    results: list[object] = []

    def start(engine: Engine) -> None:
        barrier.wait()
        try:
            results.append(migrate(engine))
        except Exception as exc:
            results.append(exc)

    threads = [threading.Thread(target=start, args=(e,)) for e in engines]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert results == [SCHEMA_VERSION] * len(engines)
    assert _user_version(engines[0]) == SCHEMA_VERSION
    for engine in engines:
        engine.dispose()
