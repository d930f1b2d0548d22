"""Run records: one interface, two backends (SQLite file, PostgreSQL URL), and a local spool
so that no record is ever lost.

The database layer is SQLAlchemy Core 2.x (with psycopg 3 for PostgreSQL): the same table,
the same idempotent insert (``ON CONFLICT (run_id) DO NOTHING``) and the same queries on both.
``db`` is a file path (SQLite, WAL mode, the embedded default) or a URL
``postgresql://user@host:port/dbname`` (``postgresql+psycopg://`` is implied).

One row per run in table ``runs`` (columns in ``docs/records.md``): serial, variant,
station, operator, start/end times (UTC ISO 8601), verdict and reasons, k6, phase_k6, c6, the
peak-to-peak ripple before/after, capture paths and SHA-256, the calibrated block's CRC and
sequence, tool and layout versions, what lot statistics read besides (the limits in force as
JSON text, the error step, phase_c6, the fit's R^2 and RMS, the run's kind and its failure
causes), and last the fit record and the whole record as JSON
(:class:`~eol_cal.station.record.RunRecord`; :func:`row_values` is the one mapping from a
record to its columns). Table ``schema_version`` holds :data:`SCHEMA_VERSION`; older databases
(version 1: written before it existed) are brought up by :func:`migrate`. Reading the records:
:mod:`eol_cal.station.records_query`.

When the database cannot be written - locked beyond the timeout, its directory missing (a share
not mounted), the server down, read-only, corrupt - the record is written as one JSON file into
the spool directory and inserted later (:mod:`eol_cal.station.spool`). The insert is keyed by
the record's ``run_id``, so a flush interrupted between the insert and the spool file's removal
inserts nothing twice, and many writers at once neither lose nor duplicate a record.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.dialects import postgresql as pg_dialect
from sqlalchemy.dialects import sqlite as sqlite_dialect
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.pool import ConnectionPoolEntry, NullPool

from eol_cal.errors import EolCalError
from eol_cal.station.record import KINDS, RunRecord

SPOOL_SCHEMA = "eol-cal/spooled-record/1"
#: the database layout this code writes (1: the SQLite table of eol-cal before schema_version)
SCHEMA_VERSION = 4
#: seconds a write waits for another connection's lock (or for the server) before spooling
DEFAULT_LOCK_TIMEOUT_S = 5.0

_metadata = sa.MetaData()
runs = sa.Table(
    "runs", _metadata,
    sa.Column("run_id", sa.Text, primary_key=True),
    sa.Column("serial", sa.Text, nullable=False),
    sa.Column("variant", sa.Text),
    sa.Column("started_at", sa.Text, nullable=False),
    sa.Column("ended_at", sa.Text),
    sa.Column("verdict", sa.Text, sa.CheckConstraint("verdict IN ('pass', 'fail', 'error')"), nullable=False),
    sa.Column("reasons", sa.Text, nullable=False),
    sa.Column("k6", sa.Float),
    sa.Column("phase_k6", sa.Float),
    sa.Column("c6", sa.Float),
    sa.Column("pp_before_pct", sa.Float),
    sa.Column("pp_after_pct", sa.Float),
    sa.Column("improvement_pct", sa.Float),
    sa.Column("capture_before", sa.Text),
    sa.Column("sha256_before", sa.Text),
    sa.Column("capture_after", sa.Text),
    sa.Column("sha256_after", sa.Text),
    sa.Column("block_crc32", sa.Text),
    sa.Column("block_sequence", sa.Integer),
    sa.Column("tool_version", sa.Text),
    sa.Column("layout_version", sa.Integer),
    sa.Column("report_dir", sa.Text),
    # version 2
    sa.Column("station", sa.Text),
    sa.Column("operator", sa.Text),
    # version 3: what lot statistics need besides the values above, so they never parse record_json
    sa.Column("limits_json", sa.Text),
    sa.Column("error_step", sa.Text),
    sa.Column("phase_c6", sa.Float),
    sa.Column("fit_r2", sa.Float),
    sa.Column("fit_rms_nm", sa.Float),
    # version 4: the run's kind (lot statistics take production runs) and why it did not pass
    sa.Column("kind", sa.Text, sa.CheckConstraint(f"kind IN ({', '.join(repr(k) for k in KINDS)})")),
    sa.Column("causes", sa.Text),
    # the documents last: SQLite reads a row's columns in order, through the overflow pages of
    # the kB of JSON before them (a database created at version 3; a migrated one adds its new
    # columns after them)
    sa.Column("fit_json", sa.Text),
    sa.Column("record_json", sa.Text, nullable=False),
    sa.Index("runs_serial", "serial"),
    sa.Index("runs_started", "started_at"),
    sa.Index("runs_variant_station", "variant", "station"),
    sa.Index("runs_kind_serial", "kind", "serial"),
)
schema_version = sa.Table("schema_version", _metadata, sa.Column("version", sa.Integer, nullable=False))
COLUMN_NAMES = tuple(c.name for c in runs.columns)
#: columns added by each migration (version: names; their types are the table's)
_ADDED = {2: ("station", "operator"), 3: ("limits_json", "error_step", "phase_c6", "fit_r2", "fit_rms_nm"),
          4: ("kind", "causes")}


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
        from eol_cal.inputs import check_regular

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
    from eol_cal.errors import InputError

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


def version_of(con: Connection) -> int | None:
    """The layout of the database: None when empty, 1 for the table without schema_version."""
    insp = sa.inspect(con)
    if insp.has_table("schema_version"):
        v = con.execute(sa.select(sa.func.max(schema_version.c.version))).scalar()
        return int(v) if v is not None else 1
    return 1 if insp.has_table("runs") else None


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


def _ensure_schema(con: Connection) -> None:
    refuse_foreign(con)
    v = version_of(con)
    if v is None and con.dialect.name == "postgresql":
        # two stations writing the first record of a new database at once: one creates
        con.execute(sa.text("SELECT pg_advisory_xact_lock(7413001)"))
        v = version_of(con)
    if v is None:
        _metadata.create_all(con)
        con.execute(schema_version.insert().values(version=SCHEMA_VERSION))
    elif v != SCHEMA_VERSION:
        raise SchemaError(f"records database at schema version {v}, this tool writes version "
                          f"{SCHEMA_VERSION}: migrate it first")


def record_row(record: RunRecord) -> dict[str, Any]:
    """The ``runs`` row of a record: :func:`row_values` plus the record (and its fit) as JSON."""
    doc = record.to_json()
    fit = doc["fit"]
    return {**row_values(record),
            "fit_json": json.dumps(fit, allow_nan=False) if fit is not None else None,
            "record_json": json.dumps(doc, allow_nan=False)}


def _num(x: float) -> float | None:
    return None if x != x else x  # NaN: NULL


def row_values(record: RunRecord) -> dict[str, Any]:
    """The columns of a record's row, except the JSON documents ``fit_json`` and ``record_json``.

    The one mapping from a record to its columns: the insert, the migrations and the lot
    statistics of parsed records (:mod:`eol_cal.lot.columns`) all use it.
    """
    cal = record.block("calibrated")
    cap = record.captures
    lim = record.limits
    limits_doc = None if lim is None else {**lim.to_dict(), "sha256": record.limits_sha256}
    return {
        "run_id": record.run_id,
        "serial": record.serial,
        "variant": None if lim is None else lim.variant,
        "started_at": record.started_at,
        "ended_at": record.ended_at,
        "verdict": record.verdict,
        "reasons": json.dumps(list(record.reasons)),
        **{q: _num(record.value(q)) for q in ("k6", "phase_k6", "c6", "pp_before_pct", "pp_after_pct",
                                             "improvement_pct", "phase_c6", "fit_r2", "fit_rms_nm")},
        "capture_before": cap["before"].path if "before" in cap else None,
        "sha256_before": cap["before"].sha256 if "before" in cap else None,
        "capture_after": cap["after"].path if "after" in cap else None,
        "sha256_after": cap["after"].sha256 if "after" in cap else None,
        "block_crc32": None if cal is None else cal.crc32,
        "block_sequence": None if cal is None else cal.sequence,
        "tool_version": record.tool_version,
        "layout_version": record.layout_version,
        "report_dir": record.report_dir,
        "station": record.station_name,
        "operator": record.operator,
        "limits_json": None if limits_doc is None else json.dumps(limits_doc, sort_keys=True, allow_nan=False),
        "error_step": None if record.error is None else record.error.step,
        "kind": record.kind,
        "causes": json.dumps(record.causes()),
    }


def _insert(con: Connection, rows: list[dict[str, Any]]) -> int:
    dialect = pg_dialect if con.dialect.name == "postgresql" else sqlite_dialect
    stmt = dialect.insert(runs).on_conflict_do_nothing(index_elements=["run_id"]).returning(runs.c.run_id)
    return len(con.execute(stmt, rows).all()) if rows else 0


def insert_records(db: str | Path, records: Sequence[RunRecord], timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> int:
    """Insert records in one transaction; an existing ``run_id`` is left as it is.

    Returns the number of rows inserted. Raises one of :data:`DB_ERRORS` when the database
    cannot be written; the caller decides to spool.
    """
    rows = [record_row(r) for r in records]
    eng = engine(db, timeout_s)
    try:
        with eng.begin() as con:
            _ensure_schema(con)
            return _insert(con, rows)
    finally:
        dispose(eng, db)


def migrate(db: str | Path, timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> tuple[int | None, int]:
    """Bring a records database to :data:`SCHEMA_VERSION` (creating it when empty).

    Version 1 (the SQLite table before ``schema_version``) gains the columns ``station`` and
    ``operator``; version 2 gains ``limits_json``, ``error_step``, ``phase_c6``, ``fit_r2`` and
    ``fit_rms_nm``; version 3 gains ``kind`` and ``causes``. The new columns are filled from each
    row's record JSON, read as a :class:`~eol_cal.station.record.RunRecord` (a record of the first
    schema migrated as it is read; a corrupt one refuses the migration, naming the run). Returns
    ``(version before, version now)``;
    ``before`` is None for a new database.
    """
    eng = engine(db, timeout_s)
    try:
        with eng.begin() as con:
            if con.dialect.name == "postgresql":
                con.execute(sa.text("SELECT pg_advisory_xact_lock(7413001)"))
            refuse_foreign(con)
            v = version_of(con)
            if v is None:
                _metadata.create_all(con)
                con.execute(schema_version.insert().values(version=SCHEMA_VERSION))
                return None, SCHEMA_VERSION
            if v > SCHEMA_VERSION:
                raise SchemaError(f"records database at schema version {v} is newer than this tool "
                                  f"({SCHEMA_VERSION})")
            added = [name for step in range(v + 1, SCHEMA_VERSION + 1) for name in _ADDED.get(step, ())]
            for name in added:
                typ = runs.c[name].type.compile(dialect=con.dialect)
                con.exec_driver_sql(f"ALTER TABLE runs ADD COLUMN {name} {typ}")
            if added:
                _fill(con, db, added)
            _metadata.create_all(con)  # the new table and indexes; existing ones are kept
            con.execute(schema_version.delete())
            con.execute(schema_version.insert().values(version=SCHEMA_VERSION))
            return v, SCHEMA_VERSION
    finally:
        dispose(eng, db)


def _fill(con: Connection, db: str | Path, names: list[str], batch: int = 2000) -> None:
    """Fill the columns ``names`` of every row from its record JSON, ``batch`` rows at a time
    (a plant's table of record documents does not fit in memory at once)."""
    stmt = runs.update().where(runs.c.run_id == sa.bindparam("_run_id")).values(
        {name: sa.bindparam(name) for name in names})
    ids = list(con.execute(sa.select(runs.c.run_id)).scalars())
    for k in range(0, len(ids), batch):
        q = sa.select(runs.c.run_id, runs.c.record_json).where(runs.c.run_id.in_(ids[k:k + batch]))
        updates = []
        for run_id, doc in con.execute(q).all():
            record = parse_record(db, run_id, doc)  # raises on a corrupt one
            values = row_values(record)
            updates.append({"_run_id": run_id, **{name: values[name] for name in names}})
        con.execute(stmt, updates)


def parse_record(db: str | Path, run_id: str, text: str) -> RunRecord:
    """The record of one row's ``record_json``; :class:`InputError` naming the database and the run."""
    from eol_cal.inputs import loads_json

    where = f"run {run_id} record_json"
    name = db_key(db) if is_url(db) else str(db)  # the file as given; a URL without its password
    doc = loads_json(str(text), name, where)
    return RunRecord.from_json(doc, f"{name}, {where}")


def one_line(exc: BaseException) -> str:
    # SQLAlchemy appends the SQL and a link on further lines; the first line says why
    if isinstance(exc, sa.exc.StatementError) and exc.orig is not None:
        exc = exc.orig
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
