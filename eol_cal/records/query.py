"""Reading the records database: filtered queries, rows, columns for lot statistics, records.

The reading side of the ``runs`` table (:mod:`eol_cal.records.tables`; the engines of
:mod:`eol_cal.records.connect`). Filters are SQL (:func:`select_runs`: variant, station, serial,
UTC day, run kind); the record documents are read as :class:`~eol_cal.records.record.RunRecord`
(:func:`query_records`), the columns lot statistics need as arrays without any document
(:func:`read_columns`).
"""

from __future__ import annotations

import gc
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from eol_cal.errors import InputError
from eol_cal.records.record import KINDS, MEASURED_KIND, RunRecord
from eol_cal.records.connect import (DB_ERRORS, DEFAULT_LOCK_TIMEOUT_S, SchemaError, db_label, dispose, engine, is_url,
                                     one_line, refuse_foreign)
from eol_cal.records.migrations import RUNS_VERSION, version_of
from eol_cal.records.rows import parse_record
from eol_cal.records.tables import runs


def kinds_of(kind: str | Sequence[str] | None) -> tuple[str, ...] | None:
    """A ``--kind`` choice as kinds: a kind, several, ``all`` (None: no filter); refuses unknown ones."""
    if kind is None or kind == "all":
        return None
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    if "all" in kinds:
        return None
    for k in kinds:
        if k not in KINDS:
            raise InputError(None, "kind", f"{k!r}: one of {', '.join(KINDS)}, or all")
    return kinds


def select_runs(variant: str | None = None, station: str | None = None, since: str | None = None,
                until: str | None = None, serial: str | None = None, day: str | None = None,
                kind: str | Sequence[str] | None = None) -> sa.Select:
    """The ``runs`` rows matching the filters, oldest first (days are UTC ``YYYY-MM-DD``, inclusive;
    ``kind``: see :func:`kinds_of`; the column came with schema version 4)."""
    q = sa.select(runs)
    kinds = kinds_of(kind)
    if kinds is not None:
        q = q.where(runs.c.kind.in_(kinds))
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
                refuse_foreign(con)
                return [dict(r._mapping) for r in con.execute(query)]
        finally:
            dispose(eng, db)
    except DB_ERRORS as exc:
        raise InputError(db_label(db), None, f"cannot read the records: {one_line(exc)}") from None


def read_columns(db: str | Path, *queries: sa.Select, min_version: int = RUNS_VERSION,
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
                refuse_foreign(con)
                v = version_of(con)
                if v is None:  # the driver's own cursor below would meet a missing table with its own error
                    raise InputError(db_label(db), None, "no records: the database has no runs table (eol-cal records "
                                                         "migrate creates one)")
                if v < min_version:
                    raise SchemaError(f"records database at schema version {v}, this needs version "
                                      f"{min_version}: migrate it first")
                results = [_fetch(con, q) for q in queries]
        finally:
            dispose(eng, db)
        return [dict(zip(names, list(zip(*rows, strict=True)) if rows else [()] * len(names), strict=True))
                for names, rows in results]
    except DB_ERRORS as exc:
        raise InputError(db_label(db), None, f"cannot read the records: {one_line(exc)}") from None
    finally:
        if collecting:
            gc.enable()


def _fetch(con: Connection, query: sa.Select) -> tuple[list[str], list[tuple[Any, ...]]]:
    # the driver's cursor on SQLAlchemy's connection (its transaction, its read-only mode)
    compiled = query.compile(dialect=con.dialect, compile_kwargs={"render_postcompile": True})
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


def query_records(db: str | Path, serial: str | None = None, day: str | None = None,
                  timeout_s: float = DEFAULT_LOCK_TIMEOUT_S, skipped: list[InputError] | None = None,
                  kind: str | Sequence[str] | None = "all") -> list[RunRecord]:
    """Records by serial and/or UTC day ``YYYY-MM-DD`` and kind (default every kind), oldest first.

    Works on every schema version (it reads only the record JSON; records of the first record
    schema are migrated as they are read). A row whose record JSON is corrupt raises
    :class:`InputError` naming the database and the run; with ``skipped`` given, it is appended
    there instead and the other records are returned.
    """
    kinds = kinds_of(kind)
    q = select_runs(serial=serial, day=day).with_only_columns(runs.c.run_id, runs.c.record_json)
    out = []
    for row in read_rows(db, q, timeout_s):
        try:
            rec = parse_record(db, row["run_id"], row["record_json"])
        except InputError as exc:
            if skipped is None:
                raise
            skipped.append(exc)
            continue
        if kinds is None or rec.kind in kinds:
            out.append(rec)
    return out


def latest_per_serial(records: Sequence[RunRecord], kind: str = MEASURED_KIND) -> dict[str, RunRecord]:
    """Each serial's latest record of ``kind`` (its latest status), by start time then run id."""
    latest: dict[str, RunRecord] = {}
    for r in sorted((r for r in records if r.kind == kind), key=lambda r: (r.started_at, r.run_id)):
        latest[r.serial] = r
    return latest


def summarise(records: Sequence[RunRecord], kind: str = MEASURED_KIND) -> dict[str, Any]:
    """Counts and pass rate of a set of records (``docs/records.md``, "Run kinds").

    ``runs``, ``pass``, ``fail``, ``error`` and ``pass_rate`` (pass / (pass + fail): the motors'
    yield, station errors counted apart; None without a judged run) count the runs of ``kind``
    (``production``; ``all``: every kind but refusals); ``kinds`` counts every kind (refusals,
    restores... apart). ``motors`` counts the serials with a run of ``kind``, ``motors_pass``
    those whose latest such run passed.
    """
    prod = [r for r in records if (r.kind != "refusal" if kind == "all" else r.kind == kind)]
    counts = {v: sum(1 for r in prod if r.verdict == v) for v in ("pass", "fail", "error")}
    judged = counts["pass"] + counts["fail"]
    latest = {r.serial: r for r in sorted(prod, key=lambda r: (r.started_at, r.run_id))}
    return {
        "runs": len(prod), **counts,
        "pass_rate": counts["pass"] / judged if judged else None,
        "motors": len(latest), "motors_pass": sum(1 for r in latest.values() if r.verdict == "pass"),
        "kinds": {k: sum(1 for r in records if r.kind == k) for k in KINDS},
    }
