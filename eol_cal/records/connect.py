"""The records database's connections: one interface, two backends (SQLite file, PostgreSQL URL).

The database layer is SQLAlchemy Core 2.x (with psycopg 3 for PostgreSQL): the same tables and
the same statements on both. ``db`` is a file path (SQLite, WAL mode, the embedded default) or a
URL ``postgresql://user@host:port/dbname`` (``postgresql+psycopg://`` is implied). Here: the
engines, a checked connection (:func:`connected`: no stored object this tool did not create), the
database's names for messages, and the errors. The tables: :mod:`eol_cal.records.tables`; their
one migration path: :mod:`eol_cal.records.migrations`; writing: :mod:`eol_cal.records.write`;
reading: :mod:`eol_cal.records.query`.
"""

from __future__ import annotations

import contextlib
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.pool import ConnectionPoolEntry, NullPool

from eol_cal.errors import EolCalError, InputError
from eol_cal.infra.inputs import check_regular

#: seconds a write waits for another connection's lock (or for the server) before spooling
DEFAULT_LOCK_TIMEOUT_S = 5.0


class RecordError(EolCalError):
    """Neither the database nor the spool could take a record (exit code 2)."""


class SchemaError(EolCalError):
    """The database holds an older (or newer) layout than this code writes (exit code 2)."""


class ForeignObjectError(SchemaError):
    """The database holds stored objects this tool did not create (triggers, views, rules): they
    would run inside its writes and reads, so it is refused, naming them (exit code 2)."""


#: what a write may raise when the database is unavailable (the caller spools)
DB_ERRORS = (sa.exc.SQLAlchemyError, sqlite3.Error, OSError, SchemaError)


def is_url(db: str | Path) -> bool:
    """True for a database URL (``postgresql://...``), False for a SQLite file path."""
    return "://" in str(db)


def _masked(url: str) -> str:
    """A URL with the password of its user part masked, without parsing it (it may not parse)."""
    scheme, _, rest = url.partition("://")
    userinfo, at, hostpart = rest.rpartition("@")
    return f"{scheme}://{userinfo.partition(':')[0]}{':***' if ':' in userinfo else ''}{at}{hostpart}" if at else url


def db_key(db: str | Path) -> str:
    """The identity of a database in the spool: the absolute file path, or the URL without password
    (a URL that does not parse: masked as typed, so that its record is still spooled)."""
    if not is_url(db):
        return str(Path(db).resolve())
    try:
        return sa.engine.make_url(_sa_url(str(db))).render_as_string(hide_password=True)
    except (sa.exc.ArgumentError, ValueError):
        return _masked(str(db))


def db_shown(db: str | Path) -> str:
    """The database as it was typed, for messages: a file path, or a URL with its password masked
    (``postgresql://eolcal:***@host/db``)."""
    return _masked(str(db)) if is_url(db) else str(db)


def db_label(db: str | Path) -> str:
    """A name of the database for titles: a file's name, or the URL as typed, password masked."""
    return db_shown(db) if is_url(db) else Path(db).name


def _sa_url(url: str) -> str:
    # psycopg 3 is the driver; a plain postgresql:// URL means it
    for plain in ("postgresql://", "postgres://"):
        if url.startswith(plain):
            return "postgresql+psycopg://" + url[len(plain):]
    return url


_engines: dict[tuple[str, float], Engine] = {}
_engines_lock = threading.Lock()


def _server_engine(url: str, timeout_s: float) -> Engine:
    # one pooled engine per URL and process: a station writes one record a minute, a benchmark many
    key = (url, timeout_s)
    with _engines_lock:
        eng = _engines.get(key)
        if eng is None or eng.pool is None:
            eng = sa.create_engine(_sa_url(url), pool_pre_ping=True, pool_size=2, max_overflow=4,
                                   connect_args={"connect_timeout": max(1, int(round(timeout_s)))})
            _engines[key] = eng
    return eng


def _sqlite_engine(db: Path, timeout_s: float, readonly: bool) -> Engine:
    url = f"sqlite:///file:{db.resolve()}?mode=ro&uri=true" if readonly else f"sqlite:///{db}"
    eng = sa.create_engine(url, poolclass=NullPool, connect_args={"timeout": timeout_s})

    @event.listens_for(eng, "connect")
    def _connect(dbapi_con: sqlite3.Connection, _rec: ConnectionPoolEntry) -> None:
        # explicit transactions: BEGIN IMMEDIATE takes the write lock up front, so a locked
        # database fails here after the timeout, not half-way through
        dbapi_con.isolation_level = None
        if not readonly:
            mode = dbapi_con.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise sqlite3.OperationalError(f"cannot switch the database to WAL mode (journal_mode={mode})")
            dbapi_con.execute("PRAGMA synchronous=FULL")
            dbapi_con.execute(f"PRAGMA busy_timeout={int(timeout_s * 1000)}")

    @event.listens_for(eng, "begin")
    def _begin(con: Connection) -> None:
        con.exec_driver_sql("BEGIN" if readonly else "BEGIN IMMEDIATE")

    return eng


def engine(db: str | Path, timeout_s: float = DEFAULT_LOCK_TIMEOUT_S, readonly: bool = False) -> Engine:
    """The SQLAlchemy engine of a records database (file path or URL)."""
    if is_url(db):
        return _server_engine(str(db), timeout_s)
    db = Path(db)
    if db.exists() and not db.is_file():
        # SQLite would open a FIFO and block in the kernel for ever (deaf to SIGTERM), or read a device
        check_regular(db, None)
    if not readonly and not db.parent.is_dir():
        # sqlite would say "unable to open database file"; say which directory is missing
        raise sqlite3.OperationalError(f"directory {db.parent} does not exist")
    return _sqlite_engine(db, timeout_s, readonly)


def dispose(eng: Engine, db: str | Path) -> None:
    if not is_url(db):
        eng.dispose()


@contextlib.contextmanager
def connected(db: str | Path, readonly: bool, what: str, timeout_s: float = DEFAULT_LOCK_TIMEOUT_S
              ) -> Iterator[Connection]:
    """A connection to an existing records database (a missing SQLite file is refused, not made),
    refused when it holds :func:`foreign_objects`; a database error inside is an
    :class:`~eol_cal.errors.InputError` saying what could not be done (``what``: "read the baseline")."""
    if not is_url(db) and not Path(db).exists():
        raise InputError(str(db), None, "database not found")
    try:
        eng = engine(db, timeout_s, readonly=readonly)
        try:
            with eng.connect() as con:
                refuse_foreign(con)
                con.rollback()  # the check's read ends here: the caller begins its own transaction
                yield con
        finally:
            dispose(eng, db)
    except DB_ERRORS as exc:
        raise InputError(db_label(db), None, f"cannot {what}: {one_line(exc)}") from None


def foreign_objects(con: Connection) -> list[str]:
    """The stored objects of the database that run code inside its statements and that this tool
    never creates: every trigger and view (SQLite); on PostgreSQL the triggers, views, rules and
    materialized views of the current schema and the event triggers, as ``"trigger NAME"``...
    (sorted). Tables and indexes are data; this tool creates no trigger, view or rule."""
    if con.dialect.name == "sqlite":
        q = "SELECT type, name FROM sqlite_master WHERE type IN ('trigger', 'view')"
    else:
        q = ("SELECT 'trigger', t.tgname || ' on ' || c.relname FROM pg_trigger t JOIN pg_class c ON c.oid = t.tgrelid "
             "WHERE NOT t.tgisinternal AND c.relnamespace = current_schema()::regnamespace "
             "UNION ALL SELECT 'view', viewname FROM pg_views WHERE schemaname = current_schema() "
             "UNION ALL SELECT 'materialized view', matviewname FROM pg_matviews WHERE schemaname = current_schema() "
             "UNION ALL SELECT 'rule', rulename || ' on ' || tablename FROM pg_rules WHERE schemaname = current_schema() "
             "UNION ALL SELECT 'event trigger', evtname FROM pg_event_trigger")
    return sorted(f"{kind} {name}" for kind, name in con.exec_driver_sql(q).all())


def refuse_foreign(con: Connection) -> None:
    """Raise :class:`ForeignObjectError` naming the database's :func:`foreign_objects` (none: nothing)."""
    found = foreign_objects(con)
    if found:
        more = f" and {len(found) - 8} more" if len(found) > 8 else ""
        raise ForeignObjectError(f"the database holds objects eol-cal did not create, which would run inside its "
                                 f"statements: {', '.join(found[:8])}{more}; drop them (or use another database)")


def one_line(exc: BaseException) -> str:
    # SQLAlchemy appends the SQL and a link on further lines; the first line says why
    if isinstance(exc, sa.exc.StatementError) and exc.orig is not None:
        exc = exc.orig
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
