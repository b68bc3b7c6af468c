"""Schema versions: old databases are upgraded in place, newer ones are refused.

The schema version lives in `PRAGMA user_version` on SQLite (a header field, transactional with
the rest of the file) and in a one-row `schema_version` table on other backends.

`migrate(engine)`:

- version 0 (a new, empty database): `SQLModel.metadata.create_all`, stamp `SCHEMA_VERSION`;
- version == `SCHEMA_VERSION`: nothing;
- older: copy the SQLite file aside (`<file>.schema-v<N>.bak`, via `VACUUM INTO`), then run
  `MIGRATIONS[N + 1]`, ..., `MIGRATIONS[SCHEMA_VERSION]` and stamp, all in one transaction
  (SQLite: `BEGIN IMMEDIATE`, which also makes a second process wait, then find nothing to do);
  a failing step leaves the database exactly as it was;
- newer: `SchemaVersionError`, one line, before anything is touched.

Changing the schema later:

1. change the tables in `models.py` (new databases get the new shape from `create_all`);
2. bump `SCHEMA_VERSION` to N and add `MIGRATIONS[N] = _to_vN`, a function taking the open
   `Connection` that turns a version N-1 database into version N with plain DDL/DML written
   for that moment (never `create_all` on the current models: a later version may have changed
   them again). `add_column` covers the common case; new tables are `CREATE TABLE` statements.
   SQLite cannot drop constraints or change a column's type in place: rebuild the table
   (create `x_new`, copy, drop `x`, rename); `PRAGMA defer_foreign_keys = ON` inside the
   migration keeps foreign key *checks* from firing mid-rebuild, but not their *actions*: never
   rebuild a table other tables reference with ON DELETE CASCADE this way (DROP TABLE deletes
   its rows first, cascading into the children, and `PRAGMA foreign_keys` cannot be switched
   off inside the migration's transaction).
3. add a test that builds a version N-1 database with rows and migrates it.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine
from sqlmodel import SQLModel

from app.core.errors import MmscleanError
from app.store import models  # noqa: F401  (registers every table on SQLModel.metadata)

log = logging.getLogger(__name__)

SCHEMA_VERSION = 7


def _to_v2(conn: Connection) -> None:
    """Version 2: per-user undo / redo of pillar labels, job cancel / attempts / result, and a
    covering index for tile reads of pillar labels."""
    conn.exec_driver_sql(
        """CREATE TABLE pillar_edit_batch (
            id INTEGER NOT NULL,
            created_at DATETIME NOT NULL,
            survey_id INTEGER NOT NULL,
            user_id INTEGER,
            state VARCHAR(32) NOT NULL,
            size INTEGER NOT NULL,
            PRIMARY KEY (id),
            FOREIGN KEY(survey_id) REFERENCES survey (id) ON DELETE CASCADE,
            FOREIGN KEY(user_id) REFERENCES user (id) ON DELETE SET NULL
        )"""
    )
    conn.exec_driver_sql(
        "CREATE INDEX ix_pillar_edit_batch_survey_id ON pillar_edit_batch (survey_id)"
    )
    conn.exec_driver_sql(
        "CREATE INDEX ix_pillar_edit_batch_user ON pillar_edit_batch (user_id, survey_id, state)"
    )
    conn.exec_driver_sql(
        """CREATE TABLE pillar_edit (
            id INTEGER NOT NULL,
            batch_id INTEGER NOT NULL,
            cell_id BIGINT NOT NULL,
            before_label INTEGER,
            after_label INTEGER,
            PRIMARY KEY (id),
            FOREIGN KEY(batch_id) REFERENCES pillar_edit_batch (id) ON DELETE CASCADE
        )"""
    )
    conn.exec_driver_sql("CREATE INDEX ix_pillar_edit_batch_id ON pillar_edit (batch_id)")
    conn.exec_driver_sql(
        "CREATE INDEX ix_pillar_label_tile ON pillar_label "
        "(survey_id, cell_id, source, label, version, confidence, user_id)"
    )
    conn.exec_driver_sql(
        "CREATE INDEX ix_pillar_label_source_updated ON pillar_label (source, updated_at)"
    )
    add_column(conn, "job", "cancel_requested BOOLEAN NOT NULL DEFAULT 0")
    add_column(conn, "job", "attempts INTEGER NOT NULL DEFAULT 0")
    add_column(conn, "job", "result JSON NOT NULL DEFAULT '{}'")


def _to_v3(conn: Connection) -> None:
    """Version 3: server-side login sessions (revocable tokens) and login throttling."""
    conn.exec_driver_sql(
        """CREATE TABLE auth_session (
            id INTEGER NOT NULL PRIMARY KEY AUTOINCREMENT,
            created_at DATETIME NOT NULL,
            user_id INTEGER NOT NULL,
            expires_at DATETIME NOT NULL,
            last_seen_at DATETIME NOT NULL,
            ended_at DATETIME,
            end_reason VARCHAR(32),
            client_address VARCHAR(64),
            user_agent VARCHAR(255),
            FOREIGN KEY(user_id) REFERENCES user (id) ON DELETE CASCADE
        )"""
    )
    conn.exec_driver_sql("CREATE INDEX ix_auth_session_user ON auth_session (user_id, ended_at)")
    conn.exec_driver_sql(
        """CREATE TABLE login_throttle (
            id INTEGER NOT NULL,
            kind VARCHAR(16) NOT NULL,
            "key" VARCHAR(255) NOT NULL,
            failures INTEGER NOT NULL,
            last_failure_at DATETIME NOT NULL,
            locked_until DATETIME,
            PRIMARY KEY (id),
            CONSTRAINT uq_login_throttle_key UNIQUE (kind, "key")
        )"""
    )


def _to_v4(conn: Connection) -> None:
    """Version 4: versions only grow. Erased pillar labels leave a tombstone holding the
    pillar's version, edits remember the version their last step left (undo / redo check it),
    and replaced review rows never get an id back (`issued_id`)."""
    conn.exec_driver_sql(
        """CREATE TABLE pillar_tombstone (
            survey_id INTEGER NOT NULL,
            cell_id BIGINT NOT NULL,
            version INTEGER NOT NULL,
            user_id INTEGER,
            updated_at DATETIME NOT NULL,
            PRIMARY KEY (survey_id, cell_id),
            FOREIGN KEY(survey_id) REFERENCES survey (id) ON DELETE CASCADE,
            FOREIGN KEY(user_id) REFERENCES user (id) ON DELETE SET NULL
        ) WITHOUT ROWID"""
    )
    conn.exec_driver_sql(
        """CREATE TABLE issued_id (
            name VARCHAR(64) NOT NULL,
            last_id INTEGER NOT NULL,
            PRIMARY KEY (name)
        )"""
    )
    add_column(conn, "pillar_edit", "version INTEGER")
    add_column(conn, "pillar_edit", "version_before INTEGER")
    conn.exec_driver_sql(
        "CREATE INDEX IF NOT EXISTS ix_pillar_edit_cell_version ON pillar_edit (cell_id, version)"
    )


def _to_v5(conn: Connection) -> None:
    """Version 5: the sensor kind of surveys and models. Every model before was trained for
    profile scanners; surveys of the KITTI readers are rotating (HDL-64E); the others are
    told on their next run (empty note: not looked at yet)."""
    add_column(conn, "survey", "sensor_kind VARCHAR(16) DEFAULT 'unknown' NOT NULL")
    add_column(conn, "survey", "sensor_note VARCHAR(255) DEFAULT '' NOT NULL")
    add_column(conn, "model_version", "sensor_kind VARCHAR(16) DEFAULT 'profile' NOT NULL")
    conn.exec_driver_sql(
        "UPDATE survey SET sensor_kind = 'rotating', sensor_note = format || ' reader: HDL-64E'"
        " WHERE format IN ('semantickitti', 'kitti-raw')"
    )


def _to_v6(conn: Connection) -> None:
    """Version 6: work areas, stretches of a survey's drive assigned, labelled and signed off
    (`app.store.work_areas`)."""
    conn.exec_driver_sql(
        """CREATE TABLE work_area (
            id INTEGER NOT NULL,
            created_at DATETIME NOT NULL,
            updated_at DATETIME NOT NULL,
            version INTEGER NOT NULL,
            survey_id INTEGER NOT NULL,
            area_index INTEGER NOT NULL,
            station_start DOUBLE NOT NULL,
            station_end DOUBLE NOT NULL,
            x_min DOUBLE NOT NULL,
            y_min DOUBLE NOT NULL,
            x_max DOUBLE NOT NULL,
            y_max DOUBLE NOT NULL,
            assignee_id INTEGER,
            reviewer_id INTEGER,
            state VARCHAR(32) NOT NULL,
            comment VARCHAR(1000) NOT NULL,
            decided_by INTEGER,
            decided_at DATETIME,
            PRIMARY KEY (id),
            CONSTRAINT uq_work_area_index UNIQUE (survey_id, area_index),
            FOREIGN KEY(survey_id) REFERENCES survey (id) ON DELETE CASCADE,
            FOREIGN KEY(assignee_id) REFERENCES user (id) ON DELETE SET NULL,
            FOREIGN KEY(reviewer_id) REFERENCES user (id) ON DELETE SET NULL,
            FOREIGN KEY(decided_by) REFERENCES user (id) ON DELETE SET NULL
        )"""
    )
    conn.exec_driver_sql("CREATE INDEX ix_work_area_survey_id ON work_area (survey_id)")
    conn.exec_driver_sql("CREATE INDEX ix_work_area_state ON work_area (state)")


def _to_v7(conn: Connection) -> None:
    """Version 7: reviewers' corrections of clutter instances (points taken out of an
    instance, missed objects added; `app.store.clutter_corrections`). IF NOT EXISTS: tests
    build older databases from today's tables, this one included."""
    conn.exec_driver_sql(
        """CREATE TABLE IF NOT EXISTS clutter_correction (
            id INTEGER NOT NULL,
            created_at DATETIME NOT NULL,
            survey_id INTEGER NOT NULL,
            frame_id VARCHAR(64) NOT NULL,
            instance_id INTEGER NOT NULL,
            kind VARCHAR(16) NOT NULL,
            points BLOB NOT NULL,
            point_count INTEGER NOT NULL,
            user_id INTEGER,
            PRIMARY KEY (id),
            FOREIGN KEY(survey_id) REFERENCES survey (id) ON DELETE CASCADE,
            FOREIGN KEY(instance_id) REFERENCES clutter_instance (id) ON DELETE CASCADE,
            FOREIGN KEY(user_id) REFERENCES user (id) ON DELETE SET NULL
        )"""
    )
    for name, columns in (
        ("ix_clutter_correction_survey_id", "survey_id"),
        ("ix_clutter_correction_frame", "survey_id, frame_id"),
        ("ix_clutter_correction_instance_id", "instance_id"),
    ):
        conn.exec_driver_sql(f"CREATE INDEX IF NOT EXISTS {name} ON clutter_correction ({columns})")


# target version -> function upgrading a database from version - 1 to it (runs in a transaction)
MIGRATIONS: dict[int, Callable[[Connection], None]] = {
    2: _to_v2,
    3: _to_v3,
    4: _to_v4,
    5: _to_v5,
    6: _to_v6,
    7: _to_v7,
}

_VERSION_TABLE = sa.Table(
    "schema_version",
    sa.MetaData(),
    sa.Column("version", sa.Integer, nullable=False),
)


class StoreError(MmscleanError):
    """The database cannot be opened or used as an mmsclean database."""

    exit_code = 2
    http_status = 503


class SchemaVersionError(StoreError):
    """The database was written by a newer mmsclean than this one."""


def describe(engine: Engine) -> str:
    """How to name the database in messages: the SQLite file, or the URL without password."""
    url = engine.url
    if url.get_backend_name() == "sqlite":
        return url.database or ":memory:"
    return url.render_as_string(hide_password=True)


def _uses_pragma(conn: Connection) -> bool:
    return conn.dialect.name == "sqlite"


def get_schema_version(conn: Connection) -> int:
    """The schema version stamped in the database; 0 for a database never stamped."""
    if _uses_pragma(conn):
        return int(conn.exec_driver_sql("PRAGMA user_version").scalar_one())
    if not sa.inspect(conn).has_table(_VERSION_TABLE.name):
        return 0
    value = conn.execute(sa.select(sa.func.max(_VERSION_TABLE.c.version))).scalar()
    return int(value or 0)


def set_schema_version(conn: Connection, version: int) -> None:
    """Stamp `version` (inside the caller's transaction)."""
    version = int(version)
    if _uses_pragma(conn):
        conn.exec_driver_sql(f"PRAGMA user_version = {version}")
        return
    _VERSION_TABLE.create(conn, checkfirst=True)
    conn.execute(_VERSION_TABLE.delete())
    conn.execute(_VERSION_TABLE.insert().values(version=version))


def has_column(conn: Connection, table: str, column: str) -> bool:
    return any(c["name"] == column for c in sa.inspect(conn).get_columns(table))


def add_column(conn: Connection, table: str, column_ddl: str) -> None:
    """`ALTER TABLE <table> ADD COLUMN <column_ddl>` unless the column is already there.

    `column_ddl` is the column as SQL, e.g. `"note TEXT"` or `"score FLOAT NOT NULL DEFAULT 0"`
    (SQLite needs a default for NOT NULL columns added to a table with rows).
    """
    name = column_ddl.split()[0].strip('"')
    if has_column(conn, table, name):
        return
    preparer = conn.dialect.identifier_preparer
    conn.exec_driver_sql(f"ALTER TABLE {preparer.quote(table)} ADD COLUMN {column_ddl}")


def _check_known(engine: Engine, version: int) -> None:
    if version > SCHEMA_VERSION:
        raise SchemaVersionError(
            f"database {describe(engine)} has schema version {version}, this mmsclean knows up "
            f"to {SCHEMA_VERSION}; upgrade mmsclean"
        )
    if version < 0:
        raise StoreError(f"database {describe(engine)} has invalid schema version {version}")


def _check_chain() -> None:
    missing = [v for v in range(2, SCHEMA_VERSION + 1) if v not in MIGRATIONS]
    if missing:  # a programming error: SCHEMA_VERSION bumped without its migration
        raise RuntimeError(f"no migration to schema version(s) {missing}")


def _read_version(engine: Engine) -> int:
    try:
        with engine.connect() as conn:
            return get_schema_version(conn)
    except sa.exc.DBAPIError as exc:
        problem = str(exc.orig).splitlines()[0] if exc.orig is not None else str(exc)
        raise StoreError(f"database {describe(engine)}: cannot open ({problem})") from exc


def _backup(engine: Engine, version: int) -> Path | None:
    """Copy an SQLite database file aside before upgrading it; None for other backends."""
    if engine.url.get_backend_name() != "sqlite":
        return None
    database = engine.url.database
    if not database or database == ":memory:" or database.startswith("file:"):
        return None
    path = Path(database)
    target = path.with_name(f"{path.name}.schema-v{version}.bak")
    n = 1
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.schema-v{version}.{n}.bak")
    # a full copy, password hashes included: created empty and owner-only first, as the database
    os.close(os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    with engine.connect() as conn:
        conn.exec_driver_sql("VACUUM INTO ?", (str(target),))
    log.info("backed up %s (schema version %d) to %s", path, version, target)
    return target


def _begin_exclusive(conn: Connection) -> None:
    if _uses_pragma(conn):
        # pysqlite opens transactions only before DML; take the write lock now so DDL and the
        # stamp are atomic and concurrent migrators queue up behind busy_timeout.
        conn.exec_driver_sql("BEGIN IMMEDIATE")
    else:
        conn.begin()


def migrate(engine: Engine) -> int:
    """Bring the database to `SCHEMA_VERSION` (see module docstring); returns that version."""
    _check_chain()
    target = SCHEMA_VERSION
    found = _read_version(engine)
    _check_known(engine, found)
    if found == target:
        return target
    if found > 0:
        _backup(engine, found)
    with engine.connect() as conn:
        _begin_exclusive(conn)
        current = get_schema_version(conn)  # again, under the lock: another process may have won
        _check_known(engine, current)
        if current == 0:
            SQLModel.metadata.create_all(conn)
            log.info("created database %s at schema version %d", describe(engine), target)
        else:
            for version in range(current + 1, target + 1):
                log.info("migrating %s to schema version %d", describe(engine), version)
                MIGRATIONS[version](conn)
        if current != target:
            set_schema_version(conn, target)
        conn.commit()
    return target
