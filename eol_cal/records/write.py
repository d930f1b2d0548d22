"""Writing run records: one idempotent insert (``ON CONFLICT (run_id) DO NOTHING``) on both backends.

The insert is keyed by the record's ``run_id``, so a flush of the spool interrupted between the
insert and the spool file's removal inserts nothing twice, and many writers at once neither lose
nor duplicate a record. When the database cannot be written - locked beyond the timeout, its
directory missing (a share not mounted), the server down, read-only, corrupt - the caller writes
the record into the spool (:mod:`eol_cal.records.spool`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sqlalchemy.dialects import postgresql as pg_dialect
from sqlalchemy.dialects import sqlite as sqlite_dialect
from sqlalchemy.engine import Connection

from eol_cal.records.connect import DEFAULT_LOCK_TIMEOUT_S, dispose, engine, refuse_foreign
from eol_cal.records.migrations import ensure_schema
from eol_cal.records.record import RunRecord
from eol_cal.records.rows import row_of
from eol_cal.records.tables import runs


def _insert(con: Connection, rows: list[dict[str, Any]]) -> int:
    dialect = pg_dialect if con.dialect.name == "postgresql" else sqlite_dialect
    stmt = dialect.insert(runs).on_conflict_do_nothing(index_elements=["run_id"]).returning(runs.c.run_id)
    return len(con.execute(stmt, rows).all()) if rows else 0


def insert_records(db: str | Path, records: Sequence[RunRecord], timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> int:
    """Insert records in one transaction; an existing ``run_id`` is left as it is (an empty
    database gets every table first).

    Returns the number of rows inserted. Raises one of :data:`eol_cal.records.connect.DB_ERRORS`
    when the database cannot be written; the caller decides to spool.
    """
    rows = [row_of(r) for r in records]
    eng = engine(db, timeout_s)
    try:
        with eng.begin() as con:
            refuse_foreign(con)
            ensure_schema(con)
            return _insert(con, rows)
    finally:
        dispose(eng, db)
