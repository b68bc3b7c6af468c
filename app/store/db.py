"""Engine and sessions (the `core/db.py` of fastapi/full-stack-fastapi-template).

SQLite is the default backend: one file in the data directory, opened in WAL mode so the web
app, the viewer and job workers read while one of them writes, with foreign keys enforced and
a 30 s busy timeout instead of immediate "database is locked" errors.

- `get_engine()`: the process's engine for a URL (default: settings), migrated on first use.
- File modes: the database holds password hashes, so an SQLite file is created 0600 (SQLite
  gives its -wal / -shm / -journal the file's mode), a folder made for it 0700, and a looser
  existing file is tightened when an engine is made (logged); `secure_dir` does the same for
  the data directory at server start.
- `session_scope()`: `with session_scope() as session:` commits on success, rolls back on error.
- `get_session()`: the FastAPI dependency (`SessionDep`); the route commits.
- Both turn a lost optimistic-concurrency race (`StaleDataError`) or a UNIQUE violation into
  `ConflictError` (409); `commit(session)` does the same for sessions used directly.
"""

from __future__ import annotations

import logging
import os
import re
import sqlite3
import stat
import threading
import time
import weakref
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any, NoReturn

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm.exc import StaleDataError
from sqlmodel import Session

from app.core.errors import ConflictError
from app.core.settings import get_settings
from app.store.migrations import migrate

log = logging.getLogger(__name__)

SQLITE_BUSY_TIMEOUT_S = 30.0
PRIVATE_DIR = 0o700
PRIVATE_FILE = 0o600
SQLITE_COMPANIONS = ("-wal", "-shm", "-journal")
SQLITE_PRAGMAS = (
    f"PRAGMA busy_timeout={int(SQLITE_BUSY_TIMEOUT_S * 1000)}",
    "PRAGMA journal_mode=WAL",
    "PRAGMA foreign_keys=ON",
    "PRAGMA synchronous=NORMAL",
)

_engines: dict[str, Engine] = {}
_engines_lock = threading.Lock()


def _database_url(url: str | None) -> str:
    return url or get_settings().database_url


def _sqlite_file(url: sa.URL) -> Path | None:
    database = url.database
    if url.get_backend_name() != "sqlite" or not database or database == ":memory:":
        return None
    if database.startswith("file:"):  # URI filename
        return None
    return Path(database)


def secure_dir(path: Path) -> Path:
    """Create `path` (and missing parents) readable by its owner only, or tighten an existing
    one that others may read (logged)."""
    path = Path(path)
    if not path.exists():
        path.mkdir(parents=True, exist_ok=True)
        path.chmod(PRIVATE_DIR)
        return path
    _tighten(path, PRIVATE_DIR)
    return path


def secure_sqlite_file(path: Path) -> None:
    """Create the database file 0600 before SQLite does (it would make it 0644, and its
    companions after it); tighten an existing file and its companions."""
    path = Path(path)
    with suppress(OSError):  # exists; or cannot be made, which SQLite then reports itself
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_FILE))
    for file in (path, *(path.with_name(path.name + s) for s in SQLITE_COMPANIONS)):
        if file.is_file():
            _tighten(file, PRIVATE_FILE)


def _tighten(path: Path, mode: int) -> None:
    """Set `path` to `mode` when group or others had any permission on it (logged)."""
    current = stat.S_IMODE(path.stat().st_mode)
    if not current & 0o077:
        return
    try:
        path.chmod(mode)
    except OSError as exc:  # not ours, or a read-only mount: say so, the owner must fix it
        log.warning("%s is open to others (mode %04o), cannot change it: %s", path, current, exc)
        return
    log.warning("%s was open to others (mode %04o); now %04o", path, current, mode)


def _execute_waiting_for_lock(cursor: sqlite3.Cursor, statement: str) -> None:
    """Run `statement`, retrying while another connection holds the lock.

    Switching a new file to WAL while other connections open it at the same moment can fail
    with "database is locked" at once: SQLite does not call the busy handler on that path.
    Retry for up to `SQLITE_BUSY_TIMEOUT_S`, as the busy timeout would have waited.
    """
    deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_S
    delay = 0.002
    while True:
        try:
            cursor.execute(statement)
            return
        except sqlite3.OperationalError as exc:
            message = str(exc).lower()
            busy = "locked" in message or "busy" in message
            if not busy or time.monotonic() >= deadline:
                raise
        time.sleep(delay)
        delay = min(delay * 2, 0.1)


def _set_sqlite_pragmas(dbapi_connection: sqlite3.Connection, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    try:
        for pragma in SQLITE_PRAGMAS:
            _execute_waiting_for_lock(cursor, pragma)
    finally:
        cursor.close()


def make_engine(url: str | None = None, **kwargs: Any) -> Engine:
    """A new engine for `url` (default: `settings.database_url`); does not touch the database.

    For an SQLite file its folder is created (0700); before each new connection opens the file
    it is created empty with mode 0600 or, when it exists, its mode and its companions' are
    tightened (see `secure_sqlite_file`); every new SQLite connection gets `SQLITE_PRAGMAS`.
    Extra keyword arguments go to `sqlalchemy.create_engine`.
    """
    parsed = sa.make_url(_database_url(url))
    if parsed.get_backend_name() == "sqlite":
        path = _sqlite_file(parsed)
        connect_args = {"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_S}
        connect_args.update(kwargs.pop("connect_args", {}))
        engine = sa.create_engine(parsed, connect_args=connect_args, **kwargs)
        if path is not None:
            path = path.resolve()
            if not path.parent.exists():
                secure_dir(path.parent)
            event.listen(engine, "do_connect", lambda *_: secure_sqlite_file(path))
        event.listen(engine, "connect", _set_sqlite_pragmas)
        return engine
    kwargs.setdefault("pool_pre_ping", True)
    return sa.create_engine(parsed, **kwargs)


def init_db(engine: Engine) -> int:
    """Create the tables of a new database or migrate an old one; returns the schema version.

    Raises `SchemaVersionError` for a database written by a newer mmsclean, `StoreError` for a
    file that is not a database.
    """
    return migrate(engine)


def get_engine(url: str | None = None) -> Engine:
    """The shared engine for `url` (default: settings), created and migrated on first call."""
    key = _database_url(url)
    with _engines_lock:
        engine = _engines.get(key)
        if engine is None:
            engine = make_engine(key)
            try:
                init_db(engine)
            except BaseException:
                engine.dispose()
                raise
            _engines[key] = engine
        return engine


def ping(engine: Engine) -> None:
    """Raise unless the database answers a trivial query (the health probe)."""
    with engine.connect() as conn:
        conn.execute(sa.text("SELECT 1"))


def dispose_engines() -> None:
    """Close every shared engine's connections and forget them (tests, shutdown)."""
    with _engines_lock:
        for engine in _engines.values():
            engine.dispose()
        _engines.clear()


_STALE_TABLE = re.compile(r"on table '([^']+)'")
_UNIQUE_SQLITE = re.compile(r"UNIQUE constraint failed: (.+)")


def as_conflict(exc: BaseException) -> ConflictError | None:
    """The `ConflictError` a stale version or a UNIQUE violation means; None for other errors."""
    if isinstance(exc, StaleDataError):
        match = _STALE_TABLE.search(str(exc))
        what = match.group(1) if match else "the record"
        return ConflictError(f"{what} was changed by someone else; reload it and try again")
    if isinstance(exc, IntegrityError):
        message = str(exc.orig)
        match = _UNIQUE_SQLITE.search(message)
        if match:
            columns = [c.strip() for c in match.group(1).split(",")]
            table = columns[0].split(".")[0]
            fields = ", ".join(c.split(".")[-1] for c in columns)
            return ConflictError(f"{table} with the same {fields} already exists")
        if "duplicate key" in message or "unique constraint" in message.lower():
            return ConflictError(message.splitlines()[0])
    return None


@contextmanager
def write_transaction(session: Session) -> Iterator[None]:
    """Take the database's write lock now, before reading what a write depends on; roll back
    if the block raises (a refused write must not keep the lock). The block should commit.

    pysqlite opens a transaction only at the first INSERT / UPDATE / DELETE, so the reads
    before it (a version check, the "before" of an undo record) would run outside the write's
    transaction and another writer could commit in between. `BEGIN IMMEDIATE` makes the
    read-check-write one transaction. Writers of this process queue on a lock first: SQLite's
    busy handler polls with sleeps of up to 100 ms, so 20 threads contending through it wait
    far longer (p99) than in a queue; other processes (job workers) still wait behind
    `busy_timeout`. Nothing to begin when the transaction already wrote (it holds the lock).
    SQLite is the store mmsclean ships with; another backend would need row locks instead.
    """
    with _write_queue(session.get_bind()):
        conn = session.connection()
        if conn.dialect.name == "sqlite" and not conn.connection.driver_connection.in_transaction:
            conn.exec_driver_sql("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            session.rollback()
            raise


_write_queues: weakref.WeakKeyDictionary[Engine, threading.RLock] = weakref.WeakKeyDictionary()


def _write_queue(engine: Engine) -> threading.RLock:
    """The engine's in-process writer lock (re-entrant: a write may call another)."""
    with _engines_lock:
        return _write_queues.setdefault(engine, threading.RLock())


def commit(session: Session) -> None:
    """`session.commit()`, raising `ConflictError` for a stale version or a duplicate."""
    try:
        session.commit()
    except (StaleDataError, IntegrityError) as exc:
        _raise_as_conflict(session, exc)


def _raise_as_conflict(session: Session, exc: StaleDataError | IntegrityError) -> NoReturn:
    """Roll back, then raise the ConflictError that `exc` means (or `exc` itself)."""
    session.rollback()
    conflict = as_conflict(exc)
    if conflict is None:
        raise exc
    raise conflict from exc


@contextmanager
def session_scope(engine: Engine | None = None) -> Iterator[Session]:
    """A session that commits when the block ends and rolls back if it raises.

    Objects stay readable after the block (`expire_on_commit=False`). Conflicts (stale version,
    duplicate) raise `ConflictError`; other errors propagate unchanged.
    """
    session = Session(engine or get_engine(), expire_on_commit=False)
    try:
        yield session
        session.commit()
    except (StaleDataError, IntegrityError) as exc:
        _raise_as_conflict(session, exc)
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def get_session() -> Iterator[Session]:
    """FastAPI dependency: one session per request on the shared engine; the route commits."""
    with Session(get_engine()) as session:
        try:
            yield session
        except (StaleDataError, IntegrityError) as exc:
            _raise_as_conflict(session, exc)
