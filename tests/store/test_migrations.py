"""Schema versions: new databases are stamped, old ones upgraded in place, newer ones refused."""

from __future__ import annotations

import stat
import threading
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine
from sqlmodel import Session, SQLModel, select

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
from app.store.models import Job, LabelSource, PillarEditBatch, PillarLabel, Survey
from app.store.pillar_labels import NO_LABEL, human_columns, undo, write_labels


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


NEXT = SCHEMA_VERSION + 1  # a made-up next version for the upgrade tests


def _to_next(conn: Connection) -> None:
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
    assert _user_version(engine) == SCHEMA_VERSION
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", NEXT)
    monkeypatch.setitem(MIGRATIONS, NEXT, _to_next)

    reopened = make_engine(f"sqlite:///{db_path}")
    assert init_db(reopened) == NEXT

    assert _user_version(reopened) == NEXT
    with reopened.connect() as conn:
        assert has_column(conn, "pillar_label", "note")
        rows = conn.exec_driver_sql("SELECT cell_id, label, note FROM pillar_label ORDER BY 1")
        assert rows.all() == [(c, c % 4, "") for c in range(5)]
        assert conn.exec_driver_sql("PRAGMA foreign_key_check").all() == []
    # the version 1 file was copied aside first, complete
    backup = db_path.with_name(db_path.name + f".schema-v{SCHEMA_VERSION}.bak")
    assert stat.S_IMODE(backup.stat().st_mode) == 0o600  # password hashes: owner only
    copy = make_engine(f"sqlite:///{backup}")
    assert _user_version(copy) == SCHEMA_VERSION
    with copy.connect() as conn:
        assert not has_column(conn, "pillar_label", "note")
        assert conn.exec_driver_sql("SELECT count(*) FROM pillar_label").scalar() == 5
    copy.dispose()
    # and a second start finds nothing to do
    assert migrate(reopened) == NEXT
    assert len(list(db_path.parent.glob("*.bak"))) == 1
    reopened.dispose()


def test_migrations_run_in_order_from_the_stored_version(
    engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    ran: list[int] = []
    top = SCHEMA_VERSION + 3
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", top)
    for version in (top, SCHEMA_VERSION + 1, SCHEMA_VERSION + 2):
        monkeypatch.setitem(MIGRATIONS, version, lambda conn, v=version: ran.append(v))
    assert migrate(engine) == top
    assert ran == [SCHEMA_VERSION + 1, SCHEMA_VERSION + 2, top]
    assert _user_version(engine) == top


def test_failing_migration_leaves_the_database_as_it_was(
    engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    _fill(engine)

    def broken(conn: Connection) -> None:
        _to_next(conn)
        conn.exec_driver_sql("UPDATE pillar_label SET note = 'half-done'")
        raise RuntimeError("migration bug")

    monkeypatch.setattr(migrations, "SCHEMA_VERSION", NEXT)
    monkeypatch.setitem(MIGRATIONS, NEXT, broken)
    with pytest.raises(RuntimeError, match="migration bug"):
        migrate(engine)
    assert _user_version(engine) == SCHEMA_VERSION
    with engine.connect() as conn:
        assert not has_column(conn, "pillar_label", "note")
        assert conn.exec_driver_sql("SELECT count(*) FROM pillar_label").scalar() == 5


def test_missing_migration_is_a_programming_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", NEXT + 1)
    monkeypatch.setitem(MIGRATIONS, NEXT, _to_next)
    with pytest.raises(RuntimeError, match=rf"no migration to schema version\(s\) \[{NEXT + 1}\]"):
        migrate(make_engine("sqlite://"))


def test_database_from_a_newer_mmsclean_is_refused(engine: Engine, db_path: Path) -> None:
    _fill(engine)
    with engine.begin() as conn:
        conn.exec_driver_sql(f"PRAGMA user_version = {NEXT}")
    engine.dispose()
    reopened = make_engine(f"sqlite:///{db_path}")
    with pytest.raises(SchemaVersionError) as caught:
        init_db(reopened)
    message = str(caught.value)
    assert message == (
        f"database {db_path} has schema version {NEXT}, this mmsclean knows up to "
        f"{SCHEMA_VERSION}; upgrade mmsclean"
    )
    assert "\n" not in message and isinstance(caught.value, MmscleanError)
    assert caught.value.exit_code != 0
    assert _user_version(reopened) == NEXT  # untouched
    reopened.dispose()


def test_newer_empty_database_is_refused_before_creating_tables(db_path: Path) -> None:
    engine = make_engine(f"sqlite:///{db_path}")
    with engine.begin() as conn:
        conn.exec_driver_sql(f"PRAGMA user_version = {NEXT}")
    with pytest.raises(SchemaVersionError, match=f"schema version {NEXT}"):
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
        rows = conn.exec_driver_sql("SELECT version FROM schema_version").all()
        assert rows == [(SCHEMA_VERSION,)]
        assert conn.exec_driver_sql("PRAGMA user_version").scalar() == 0
    assert "pillar_label" in _tables(engine)

    monkeypatch.setattr(migrations, "SCHEMA_VERSION", NEXT)
    monkeypatch.setitem(MIGRATIONS, NEXT, _to_next)
    assert migrate(engine) == NEXT
    with engine.connect() as conn:
        assert conn.exec_driver_sql("SELECT version FROM schema_version").all() == [(NEXT,)]
        assert has_column(conn, "pillar_label", "note")

    monkeypatch.setattr(migrations, "SCHEMA_VERSION", SCHEMA_VERSION)
    with pytest.raises(
        SchemaVersionError,
        match=f"has schema version {NEXT}, this mmsclean knows up to {SCHEMA_VERSION}",
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


V3_TABLES = ("auth_session", "login_throttle")
V4_TABLES = ("pillar_tombstone", "issued_id")
V6_TABLES = ("work_area",)


def test_version_1_database_is_upgraded_to_2_keeping_labels(
    db_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The real version 2 migration on a database that version 1 of mmsclean wrote."""
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 1)
    monkeypatch.setattr(migrations, "MIGRATIONS", {})
    old = make_engine(f"sqlite:///{db_path}")
    with old.begin() as conn:  # the version 1 tables: today's minus what version 2 added
        for table in SQLModel.metadata.sorted_tables:
            if table.name not in (
                "pillar_edit_batch",
                "pillar_edit",
                *V3_TABLES,
                *V4_TABLES,
                *V6_TABLES,
            ):
                table.create(conn)
        conn.exec_driver_sql("DROP INDEX ix_pillar_label_tile")
        conn.exec_driver_sql("DROP INDEX ix_pillar_label_source_updated")
        for column in ("cancel_requested", "attempts", "result"):
            conn.exec_driver_sql(f"ALTER TABLE job DROP COLUMN {column}")
        conn.exec_driver_sql("PRAGMA user_version = 1")
        conn.exec_driver_sql(
            "INSERT INTO survey (id, created_at, updated_at, version, name, format, source_path,"
            " frame_count, point_count, has_reference_labels, poses_estimated, origin_x,"
            " origin_y, origin_z) VALUES (1, '2026-01-01', '2026-01-01', 1, 's', 'sim', '/s',"
            " 0, 0, 0, 0, 0, 0, 0)"
        )
        conn.exec_driver_sql(
            "INSERT INTO job (id, created_at, updated_at, kind, config, status, progress,"
            " message) VALUES (1, '2026-01-01', '2026-01-01', 'run:phantom', '{}', 'queued',"
            " 0, '')"
        )
    old.dispose()
    monkeypatch.undo()
    engine = make_engine(f"sqlite:///{db_path}")
    assert init_db(engine) == SCHEMA_VERSION
    with Session(engine) as session:
        job = session.get(Job, 1)
        assert (job.cancel_requested, job.attempts, job.result) == (False, 0, {})
        session.add(PillarEditBatch(survey_id=1, size=0))
        session.commit()
    with engine.connect() as conn:
        indexes = {r[1] for r in conn.exec_driver_sql("PRAGMA index_list(pillar_label)")}
        assert {"ix_pillar_label_tile", "ix_pillar_label_source_updated"} <= indexes
        assert conn.exec_driver_sql("PRAGMA foreign_key_check").all() == []
    engine.dispose()


def _upgraded(
    old: Engine, db_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> tuple[Engine, Engine]:
    """The old database migrated by the real migrations, and a new database to compare with."""
    old.dispose()
    monkeypatch.undo()
    engine = make_engine(f"sqlite:///{db_path}")
    assert init_db(engine) == SCHEMA_VERSION
    fresh = make_engine(f"sqlite:///{tmp_path / 'fresh.sqlite3'}")
    init_db(fresh)
    return engine, fresh


def _columns(engine: Engine, table: str) -> list[tuple]:
    with engine.connect() as conn:
        return [tuple(r) for r in conn.exec_driver_sql(f"PRAGMA table_info({table})")]


def test_version_2_database_gets_login_sessions_and_throttling(
    db_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The real version 3 migration: the new tables have the shape a new database gets, a
    session row goes with its user, and an ended session's id is never reused."""
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 2)
    monkeypatch.setattr(migrations, "MIGRATIONS", {2: MIGRATIONS[2]})
    old = make_engine(f"sqlite:///{db_path}")
    with old.begin() as conn:
        for table in SQLModel.metadata.sorted_tables:
            if table.name not in (*V3_TABLES, *V4_TABLES, *V6_TABLES):
                table.create(conn)
        conn.exec_driver_sql("PRAGMA user_version = 2")
        conn.exec_driver_sql(
            "INSERT INTO user (id, created_at, updated_at, version, username, hashed_password,"
            " role, is_active) VALUES (1, '2026-01-01', '2026-01-01', 1, 'ann', 'x',"
            " 'annotator', 1)"
        )
    engine, fresh = _upgraded(old, db_path, tmp_path, monkeypatch)
    for table in V3_TABLES:
        assert _columns(engine, table) == _columns(fresh, table)
    fresh.dispose()
    with engine.begin() as conn:
        insert = (
            "INSERT INTO auth_session (created_at, user_id, expires_at, last_seen_at)"
            " VALUES ('2026-01-01', 1, '2026-01-02', '2026-01-01')"
        )
        first = conn.exec_driver_sql(insert).lastrowid
        conn.exec_driver_sql("DELETE FROM auth_session")
        assert conn.exec_driver_sql(insert).lastrowid == first + 1
        conn.exec_driver_sql("DELETE FROM user WHERE id = 1")
        assert conn.exec_driver_sql("SELECT count(*) FROM auth_session").scalar() == 0
        assert conn.exec_driver_sql("PRAGMA foreign_key_check").all() == []
    engine.dispose()


def test_version_3_database_gets_tombstones_edit_versions_and_issued_ids(
    db_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The real version 4 migration: the new tables and columns have the shape a new database
    gets; an undo stack from before keeps working (by label), and erases leave tombstones."""
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 3)
    monkeypatch.setattr(migrations, "MIGRATIONS", {v: MIGRATIONS[v] for v in (2, 3)})
    old = make_engine(f"sqlite:///{db_path}")
    with old.begin() as conn:
        for table in SQLModel.metadata.sorted_tables:
            if table.name not in (*V4_TABLES, *V6_TABLES):
                table.create(conn)
        conn.exec_driver_sql("DROP INDEX ix_pillar_edit_cell_version")
        for column in ("version", "version_before"):
            conn.exec_driver_sql(f"ALTER TABLE pillar_edit DROP COLUMN {column}")
        conn.exec_driver_sql("PRAGMA user_version = 3")
    _fill(old)  # five human labels at version 1
    with old.begin() as conn:  # one undoable batch of cell 2 (label 2), as version 3 wrote it
        conn.exec_driver_sql(
            "INSERT INTO pillar_edit_batch (id, created_at, survey_id, state, size)"
            " VALUES (1, '2026-01-01', 1, 'done', 1)"
        )
        conn.exec_driver_sql(
            "INSERT INTO pillar_edit (batch_id, cell_id, before_label, after_label)"
            " VALUES (1, 2, NULL, 2)"
        )
    engine, fresh = _upgraded(old, db_path, tmp_path, monkeypatch)
    for table in (*V4_TABLES, "pillar_edit"):
        assert _columns(engine, table) == _columns(fresh, table)
    fresh.dispose()
    with engine.connect() as conn:
        indexes = {r[1] for r in conn.exec_driver_sql("PRAGMA index_list(pillar_edit)")}
        assert "ix_pillar_edit_cell_version" in indexes
    with Session(engine) as session:
        assert undo(session, 1, None).versions.tolist() == [2]  # by label: unchanged since
        assert human_columns(session, 1, [2])[1].tolist() == [2]  # erased, version kept
        assert write_labels(session, 1, None, [3], [NO_LABEL], [1]).versions.tolist() == [2]
    with engine.connect() as conn:
        tombstones = conn.exec_driver_sql("SELECT cell_id, version FROM pillar_tombstone")
        assert sorted(tombstones.all()) == [(2, 2), (3, 2)]
        assert conn.exec_driver_sql("PRAGMA foreign_key_check").all() == []
    engine.dispose()


def test_version_4_database_gets_sensor_kinds(
    db_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The real version 5 migration: surveys and models get their sensor kind, with the shape a
    new database gets; KITTI surveys are rotating, the models before were all profile models."""
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 4)
    monkeypatch.setattr(migrations, "MIGRATIONS", {v: MIGRATIONS[v] for v in (2, 3, 4)})
    old = make_engine(f"sqlite:///{db_path}")
    with old.begin() as conn:
        SQLModel.metadata.create_all(conn)
        conn.exec_driver_sql("DROP TABLE work_area")
        for table, column in (
            ("survey", "sensor_kind"),
            ("survey", "sensor_note"),
            ("model_version", "sensor_kind"),
        ):
            conn.exec_driver_sql(f"ALTER TABLE {table} DROP COLUMN {column}")
        conn.exec_driver_sql("PRAGMA user_version = 4")
        for i, fmt in enumerate(("semantickitti", "las", "sim"), start=1):
            conn.exec_driver_sql(
                "INSERT INTO survey (id, created_at, updated_at, version, name, format,"
                " source_path, frame_count, point_count, has_reference_labels, poses_estimated,"
                f" origin_x, origin_y, origin_z) VALUES ({i}, '2026-01-01', '2026-01-01', 1,"
                f" 's{i}', '{fmt}', '/s', 0, 0, 0, 0, 0, 0, 0)"
            )
        conn.exec_driver_sql(
            "INSERT INTO model_version (id, created_at, updated_at, version, pipeline, name,"
            " checkpoint_path, metrics, trained_on, is_promoted) VALUES (1, '2026-01-01',"
            " '2026-01-01', 1, 'phantom', 'shipped:x.pt', '/x.pt', '{}', '{}', 1)"
        )
    engine, fresh = _upgraded(old, db_path, tmp_path, monkeypatch)
    for table in ("survey", "model_version"):  # same columns; added ones come last
        by_name = {c[1]: c[2:] for c in _columns(engine, table)}
        assert by_name == {c[1]: c[2:] for c in _columns(fresh, table)}
    fresh.dispose()
    with engine.connect() as conn:
        kinds = conn.exec_driver_sql("SELECT format, sensor_kind FROM survey ORDER BY id").all()
        assert kinds == [("semantickitti", "rotating"), ("las", "unknown"), ("sim", "unknown")]
        assert conn.exec_driver_sql("SELECT sensor_kind FROM model_version").scalar() == "profile"
    engine.dispose()


def test_version_5_database_gets_work_areas(
    db_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The real version 6 migration: the work area table has the shape a new database gets,
    with its indexes, and its rows go with their survey."""
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 5)
    monkeypatch.setattr(migrations, "MIGRATIONS", {v: MIGRATIONS[v] for v in range(2, 6)})
    old = make_engine(f"sqlite:///{db_path}")
    with old.begin() as conn:
        for table in SQLModel.metadata.sorted_tables:
            if table.name not in V6_TABLES:
                table.create(conn)
        conn.exec_driver_sql("PRAGMA user_version = 5")
    _fill(old)  # survey 1
    engine, fresh = _upgraded(old, db_path, tmp_path, monkeypatch)
    assert _columns(engine, "work_area") == _columns(fresh, "work_area")

    def indexes(e: Engine) -> set[tuple]:
        with e.connect() as conn:
            return {tuple(r)[1:3] for r in conn.exec_driver_sql("PRAGMA index_list(work_area)")}

    assert indexes(engine) == indexes(fresh)
    fresh.dispose()
    with engine.begin() as conn:
        conn.exec_driver_sql(
            "INSERT INTO work_area (created_at, updated_at, version, survey_id, area_index,"
            " station_start, station_end, x_min, y_min, x_max, y_max, state, comment)"
            " VALUES ('2026-01-01', '2026-01-01', 1, 1, 0, 0, 100, 0, 0, 1, 1, 'open', '')"
        )
        conn.exec_driver_sql("DELETE FROM survey WHERE id = 1")
        assert conn.exec_driver_sql("SELECT count(*) FROM work_area").scalar() == 0
        assert conn.exec_driver_sql("PRAGMA foreign_key_check").all() == []
    engine.dispose()
