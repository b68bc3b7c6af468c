"""The real version 7 migration: a version 6 database gets the clutter correction table in the
shape a new database has, with its indexes, and its rows go with their instance."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy.engine import Engine
from sqlmodel import SQLModel

from app.store import migrations
from app.store.db import init_db, make_engine
from app.store.migrations import MIGRATIONS, SCHEMA_VERSION


def _shape(engine: Engine) -> tuple[list[tuple], set[tuple]]:
    with engine.connect() as conn:
        columns = [tuple(r) for r in conn.exec_driver_sql("PRAGMA table_info(clutter_correction)")]
        indexes = {
            tuple(r)[1:3] for r in conn.exec_driver_sql("PRAGMA index_list(clutter_correction)")
        }
    return columns, indexes


def test_version_6_database_gets_clutter_corrections(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(migrations, "SCHEMA_VERSION", 6)
    monkeypatch.setattr(migrations, "MIGRATIONS", {v: MIGRATIONS[v] for v in range(2, 7)})
    old = make_engine(f"sqlite:///{tmp_path / 'old.sqlite3'}")
    with old.begin() as conn:
        for table in SQLModel.metadata.sorted_tables:
            if table.name != "clutter_correction":
                table.create(conn)
        conn.exec_driver_sql("PRAGMA user_version = 6")
        conn.exec_driver_sql(
            "INSERT INTO survey (id, created_at, updated_at, version, name, format, source_path,"
            " frame_count, point_count, has_reference_labels, poses_estimated, origin_x,"
            " origin_y, origin_z, sensor_kind, sensor_note) VALUES (1, '2026-01-01',"
            " '2026-01-01', 1, 's', 'sim', '/s', 0, 0, 0, 0, 0, 0, 0, 'unknown', '')"
        )
        conn.exec_driver_sql(
            "INSERT INTO clutter_instance (id, created_at, survey_id, frame_id, instance_index,"
            " class_name, point_count) VALUES (5, '2026-01-01', 1, 'f0', 0, 'car', 3)"
        )
    old.dispose()
    monkeypatch.undo()
    engine = make_engine(f"sqlite:///{tmp_path / 'old.sqlite3'}")
    assert init_db(engine) == SCHEMA_VERSION == 7
    fresh = make_engine(f"sqlite:///{tmp_path / 'fresh.sqlite3'}")
    init_db(fresh)
    assert _shape(engine) == _shape(fresh)
    with engine.begin() as conn:
        conn.exec_driver_sql(
            "INSERT INTO clutter_correction (created_at, survey_id, frame_id, instance_id, kind,"
            " points, point_count) VALUES ('2026-01-02', 1, 'f0', 5, 'remove', x'00000000', 1)"
        )
        conn.exec_driver_sql("DELETE FROM clutter_instance WHERE id = 5")
        assert conn.exec_driver_sql("SELECT count(*) FROM clutter_correction").scalar() == 0
    engine.dispose()
    fresh.dispose()
