"""Run records: one interface, two backends (SQLite file, PostgreSQL URL), and a local spool
so that no record is ever lost.

The database layer is SQLAlchemy Core 2.x (with psycopg 3 for PostgreSQL): the same table,
the same idempotent insert (``ON CONFLICT (run_id) DO NOTHING``) and the same queries on both.
``db`` is a file path (SQLite, WAL mode, the embedded default) or a URL
``postgresql://user@host:port/dbname`` (``postgresql+psycopg://`` is implied).

One row per motor run in table ``runs`` (columns in ``docs/records.md``): serial, variant,
station, operator, start/end times (UTC ISO 8601), verdict and reasons, k6, phase_k6, c6, the
peak-to-peak ripple before/after, capture paths and SHA-256, the block's CRC and sequence,
tool and layout versions, what lot statistics read besides (the limits in force as JSON text,
the error step, phase_c6, the fit's R^2 and RMS), and last the fit record and the whole record
as JSON. Table ``schema_version`` holds :data:`SCHEMA_VERSION`; older databases (version 1:
written before it existed) are brought up by :func:`migrate`.

When the database cannot be written - locked beyond the timeout, its directory missing (a share
not mounted), the server down, read-only, corrupt - the record is written as one JSON file into
the spool directory and inserted later (:mod:`eol_cal.station.spool`). The insert is keyed by
the record's ``run_id``, so a flush interrupted between the insert and the spool file's removal
inserts nothing twice, and many writers at once neither lose nor duplicate a record.
"""

from __future__ import annotations

import gc
import json
import sqlite3
import threading
from pathlib import Path
from typing import Any, Sequence

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.dialects import postgresql as pg_dialect
from sqlalchemy.dialects import sqlite as sqlite_dialect
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.pool import NullPool

from eol_cal.errors import EolCalError, InputError

RECORD_SCHEMA = "eol-cal/run-record/1"
SPOOL_SCHEMA = "eol-cal/spooled-record/1"
#: the database layout this code writes (1: the SQLite table of eol-cal before schema_version)
SCHEMA_VERSION = 3
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
    # the documents last: SQLite reads a row's columns in order, through the overflow pages of
    # the kB of JSON before them (a database created at version 3; a migrated one adds its new
    # columns after them)
    sa.Column("fit_json", sa.Text),
    sa.Column("record_json", sa.Text, nullable=False),
    sa.Index("runs_serial", "serial"),
    sa.Index("runs_started", "started_at"),
    sa.Index("runs_variant_station", "variant", "station"),
)
schema_version = sa.Table("schema_version", _metadata, sa.Column("version", sa.Integer, nullable=False))
COLUMN_NAMES = tuple(c.name for c in runs.columns)
#: columns added by each migration (version: names; their types are the table's)
_ADDED = {2: ("station", "operator"), 3: ("limits_json", "error_step", "phase_c6", "fit_r2", "fit_rms_nm")}


class RecordError(EolCalError):
    """Neither the database nor the spool could take a record (exit code 2)."""


class SchemaError(EolCalError):
    """The database holds an older (or newer) layout than this code writes (exit code 2)."""


#: what a write may raise when the database is unavailable (the caller spools)
DB_ERRORS = (sa.exc.SQLAlchemyError, sqlite3.Error, OSError, SchemaError)


def is_url(db: str | Path) -> bool:
    """True for a database URL (``postgresql://...``), False for a SQLite file path."""
    return "://" in str(db)


def db_key(db: str | Path) -> str:
    """The identity of a database in the spool: the absolute file path, or the URL without password."""
    if not is_url(db):
        return str(Path(db).resolve())
    return sa.engine.make_url(_sa_url(str(db))).render_as_string(hide_password=True)


def db_label(db: str | Path) -> str:
    """A name of the database for titles and messages (no password)."""
    return db_key(db) if is_url(db) else Path(db).name


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
    if readonly:
        url = f"sqlite:///file:{db.resolve()}?mode=ro&uri=true"
    else:
        url = f"sqlite:///{db}"
    eng = sa.create_engine(url, poolclass=NullPool, connect_args={"timeout": timeout_s})

    @event.listens_for(eng, "connect")
    def _connect(dbapi_con, _rec) -> None:
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


def _dispose(eng: Engine, db: str | Path) -> None:
    if not is_url(db):
        eng.dispose()


def _version(con: Connection) -> int | None:
    """The layout of the database: None when empty, 1 for the table without schema_version."""
    insp = sa.inspect(con)
    if insp.has_table("schema_version"):
        v = con.execute(sa.select(sa.func.max(schema_version.c.version))).scalar()
        return int(v) if v is not None else 1
    return 1 if insp.has_table("runs") else None


def _ensure_schema(con: Connection) -> None:
    v = _version(con)
    if v is None and con.dialect.name == "postgresql":
        # two stations writing the first record of a new database at once: one creates
        con.execute(sa.text("SELECT pg_advisory_xact_lock(7413001)"))
        v = _version(con)
    if v is None:
        _metadata.create_all(con)
        con.execute(schema_version.insert().values(version=SCHEMA_VERSION))
    elif v != SCHEMA_VERSION:
        raise SchemaError(f"records database at schema version {v}, this tool writes version "
                          f"{SCHEMA_VERSION}: migrate it first")


def _row(record: dict[str, Any]) -> dict[str, Any]:
    """The ``runs`` row of a record: :func:`row_values` plus the record (and its fit) as JSON."""
    fit = record.get("fit")
    return {**row_values(record),
            "fit_json": json.dumps(fit, allow_nan=False) if fit is not None else None,
            "record_json": json.dumps(record, allow_nan=False)}


def row_values(record: dict[str, Any]) -> dict[str, Any]:
    """The columns of a record's row, except the JSON documents ``fit_json`` and ``record_json``.

    The one mapping from a record to its columns: the insert, the migrations and the lot
    statistics of parsed records (:mod:`eol_cal.lot.columns`) all use it.
    """
    def get(*keys: str) -> Any:
        x: Any = record
        for k in keys:
            if not isinstance(x, dict) or x.get(k) is None:
                return None
            x = x[k]
        return x

    limits = record.get("limits")
    return {
        "run_id": record["run_id"],
        "serial": record["serial"],
        "variant": get("limits", "variant"),
        "started_at": record["started_at"],
        "ended_at": record.get("ended_at"),
        "verdict": record["verdict"],
        "reasons": json.dumps(record.get("reasons") or []),
        "k6": get("fit", "k6", "value"),
        "phase_k6": get("fit", "phase_k6", "value"),
        "c6": get("fit", "c6", "value"),
        "pp_before_pct": get("metrics", "pp_before_pct"),
        "pp_after_pct": get("metrics", "pp_after_pct"),
        "improvement_pct": get("metrics", "improvement_pct"),
        "capture_before": get("captures", "before", "path"),
        "sha256_before": get("captures", "before", "sha256"),
        "capture_after": get("captures", "after", "path"),
        "sha256_after": get("captures", "after", "sha256"),
        "block_crc32": get("block", "crc32"),
        "block_sequence": get("block", "sequence"),
        "tool_version": record.get("tool_version"),
        "layout_version": record.get("layout_version"),
        "report_dir": record.get("report_dir"),
        "station": _station_of(record),
        "operator": record.get("operator") or get("station", "operator"),
        "limits_json": json.dumps(limits, sort_keys=True, allow_nan=False) if isinstance(limits, dict) else None,
        "error_step": get("error", "step"),
        "phase_c6": get("fit", "phase_c6", "value"),
        "fit_r2": get("fit", "fit", "r2"),
        "fit_rms_nm": get("fit", "fit", "rms"),
    }


def _station_of(record: dict[str, Any]) -> str | None:
    # the station id as the reports read it (one rule); the column is NULL without one
    from eol_cal.report.motor import NO_STATION, station_of

    name = station_of(record)
    return None if name == NO_STATION else name


def _insert(con: Connection, rows: list[dict[str, Any]]) -> int:
    dialect = pg_dialect if con.dialect.name == "postgresql" else sqlite_dialect
    stmt = dialect.insert(runs).on_conflict_do_nothing(index_elements=["run_id"]).returning(runs.c.run_id)
    return len(con.execute(stmt, rows).all()) if rows else 0


def insert_records(db: str | Path, records: list[dict[str, Any]], timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> int:
    """Insert records in one transaction; an existing ``run_id`` is left as it is.

    Returns the number of rows inserted. Raises one of :data:`DB_ERRORS` when the database
    cannot be written; the caller decides to spool.
    """
    rows = [_row(r) for r in records]
    eng = engine(db, timeout_s)
    try:
        with eng.begin() as con:
            _ensure_schema(con)
            return _insert(con, rows)
    finally:
        _dispose(eng, db)


def migrate(db: str | Path, timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> tuple[int | None, int]:
    """Bring a records database to :data:`SCHEMA_VERSION` (creating it when empty).

    Version 1 (the SQLite table before ``schema_version``) gains the columns ``station`` and
    ``operator``; version 2 gains ``limits_json``, ``error_step``, ``phase_c6``, ``fit_r2`` and
    ``fit_rms_nm``. The new columns are filled from each row's record JSON (a corrupt one
    refuses the migration, naming the run). Returns ``(version before, version now)``;
    ``before`` is None for a new database.
    """
    eng = engine(db, timeout_s)
    try:
        with eng.begin() as con:
            if con.dialect.name == "postgresql":
                con.execute(sa.text("SELECT pg_advisory_xact_lock(7413001)"))
            v = _version(con)
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
        _dispose(eng, db)


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
            record = _record(db, {"run_id": run_id, "record_json": doc}, None)  # raises on a corrupt one
            values = row_values(record)  # type: ignore[arg-type]
            updates.append({"_run_id": run_id, **{name: values[name] for name in names}})
        con.execute(stmt, updates)


def select_runs(variant: str | None = None, station: str | None = None, since: str | None = None,
                until: str | None = None, serial: str | None = None, day: str | None = None) -> sa.Select:
    """The ``runs`` rows matching the filters, oldest first (days are UTC ``YYYY-MM-DD``, inclusive)."""
    q = sa.select(runs)
    day_of = sa.func.substr(runs.c.started_at, 1, 10)
    for col, value in ((runs.c.variant, variant), (runs.c.station, station), (runs.c.serial, serial), (day_of, day)):
        if value is not None:
            q = q.where(col == value)
    if since is not None:
        q = q.where(day_of >= since)
    if until is not None:
        q = q.where(day_of <= until)
    return q.order_by(runs.c.started_at, runs.c.run_id)


def read_rows(db: str | Path, query: sa.Select, timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> list[dict[str, Any]]:
    """Rows of ``query`` as dicts; :class:`InputError` when the database is missing or unreadable."""
    if not is_url(db) and not Path(db).exists():
        raise InputError(str(db), None, "database not found")
    try:
        eng = engine(db, timeout_s, readonly=True)
        try:
            with eng.connect() as con:
                return [dict(r._mapping) for r in con.execute(query)]
        finally:
            _dispose(eng, db)
    except DB_ERRORS as exc:
        raise InputError(db_label(db), None, f"cannot read the records: {one_line(exc)}") from None


def read_columns(db: str | Path, *queries: sa.Select, min_version: int = SCHEMA_VERSION,
                 timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> list[dict[str, Sequence[Any]]]:
    """The results of ``queries`` column-wise, each ``{column name: values in row order}``, all
    from one snapshot of the database (one read transaction, repeatable read).

    For many rows: SQLAlchemy writes the SQL, the driver's own cursor fetches the rows (on
    PostgreSQL in the binary protocol: numbers arrive as binary doubles), without a
    SQLAlchemy row object per row. :class:`InputError` when the database is missing or
    unreadable, or older than ``min_version`` (the columns the queries read came with it).
    """
    if not is_url(db) and not Path(db).exists():
        raise InputError(str(db), None, "database not found")
    collecting = gc.isenabled()
    gc.disable()  # millions of new objects, none in a cycle: the collector's passes over them are waste
    try:
        eng = engine(db, timeout_s, readonly=True)
        try:
            with eng.connect() as con:
                if con.dialect.name == "postgresql":
                    con = con.execution_options(isolation_level="REPEATABLE READ")
                v = _version(con)
                if v is not None and v < min_version:
                    raise SchemaError(f"records database at schema version {v}, this needs version "
                                      f"{min_version}: migrate it first")
                results = [_fetch(con, q) for q in queries]
        finally:
            _dispose(eng, db)
        return [dict(zip(names, list(zip(*rows)) if rows else [()] * len(names))) for names, rows in results]
    except DB_ERRORS as exc:
        raise InputError(db_label(db), None, f"cannot read the records: {one_line(exc)}") from None
    finally:
        if collecting:
            gc.enable()


def _fetch(con: Connection, query: sa.Select) -> tuple[list[str], list[tuple[Any, ...]]]:
    # the driver's cursor on SQLAlchemy's connection (its transaction, its read-only mode)
    compiled = query.compile(dialect=con.dialect)
    driver = con.connection.driver_connection
    if con.dialect.name == "postgresql":
        cur = driver.cursor(binary=True)  # type: ignore[union-attr]
        cur.execute(str(compiled), compiled.params)
    else:  # sqlite3: positional parameters
        cur = driver.cursor()  # type: ignore[union-attr]
        cur.execute(str(compiled), [compiled.params[k] for k in compiled.positiontup or ()])
    try:
        return [d[0] for d in cur.description], cur.fetchall()
    finally:
        cur.close()


def _record(db: str | Path, row: dict[str, Any], skipped: list[InputError] | None) -> dict[str, Any] | None:
    """The parsed ``record_json`` of one row; a corrupt one is refused naming the database and the
    run, or (with ``skipped``) added there and passed over."""
    from eol_cal.inputs import loads_json

    where = f"run {row.get('run_id')} record_json"
    name = db_key(db) if is_url(db) else str(db)  # the file as given; a URL without its password
    try:
        doc = loads_json(str(row["record_json"]), name, where)
        if not isinstance(doc, dict):
            raise InputError(name, where, f"a JSON {type(doc).__name__}, not a record object")
    except InputError as exc:
        if skipped is None:
            raise
        skipped.append(exc)
        return None
    return doc


def query_records(db: str | Path, serial: str | None = None, day: str | None = None,
                  timeout_s: float = DEFAULT_LOCK_TIMEOUT_S,
                  skipped: list[InputError] | None = None) -> list[dict[str, Any]]:
    """Records (the stored JSON documents) by serial and/or UTC day ``YYYY-MM-DD``, oldest first.

    Works on every schema version (it reads only the record JSON). A row whose record JSON is
    corrupt raises :class:`InputError` naming the database and the run; with ``skipped`` given,
    it is appended there instead and the other records are returned.
    """
    q = select_runs(serial=serial, day=day).with_only_columns(runs.c.run_id, runs.c.record_json)
    docs = (_record(db, r, skipped) for r in read_rows(db, q, timeout_s))
    return [d for d in docs if d is not None]


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts and pass rate of a set of records.

    ``pass_rate`` is pass / (pass + fail): the motors' yield, with station errors (which say
    nothing about the motor) counted apart; None without a judged run. ``motors_pass`` counts
    the motors whose latest run passed.
    """
    counts = {v: sum(1 for r in records if r.get("verdict") == v) for v in ("pass", "fail", "error")}
    judged = counts["pass"] + counts["fail"]
    latest: dict[str, str] = {}
    for r in sorted(records, key=lambda r: r.get("started_at", "")):
        latest[r["serial"]] = r.get("verdict")
    return {
        "runs": len(records), **counts,
        "pass_rate": counts["pass"] / judged if judged else None,
        "motors": len(latest), "motors_pass": sum(1 for v in latest.values() if v == "pass"),
    }


def one_line(exc: BaseException) -> str:
    # SQLAlchemy appends the SQL and a link on further lines; the first line says why
    if isinstance(exc, sa.exc.StatementError) and exc.orig is not None:
        exc = exc.orig
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
