"""The records database's one layout version and its one migration path, for every table.

Table ``schema_version`` holds the layout of all the tables of :mod:`eol_cal.records.tables`
(runs, baselines, gate rules) as one number, :data:`SCHEMA_VERSION`. A new database is created
whole at that version by its first writer (a record, a baseline, a gate change) or by
``eol-cal records migrate``; a database at another version is refused by every writer ("migrate
it first") and brought up by :func:`migrate`, in one transaction, under one lock
(:data:`LOCK_ID`, PostgreSQL's advisory lock; SQLite's write lock is taken up front):

- 1 (the SQLite ``runs`` table before ``schema_version``) -> 2: ``station``, ``operator``;
- 2 -> 3: ``limits_json``, ``error_step``, ``phase_c6``, ``fit_r2``, ``fit_rms_nm``;
- 3 -> 4: ``kind``, ``causes`` (the new ``runs`` columns filled from each row's record JSON);
- 4 -> 5: the baseline and gate tables join the one version. Up to version 4 they kept their own
  (``baseline_schema_version`` 1 or 2, ``gate_schema_version`` 1); a baseline of layout 1 gains
  ``kind`` (production runs) and ``stations`` (its one station, or all), both version tables are
  dropped, and tables a database did not have yet are created.
"""

from __future__ import annotations

import json
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from eol_cal.records.connect import DEFAULT_LOCK_TIMEOUT_S, SchemaError, dispose, engine, refuse_foreign
from eol_cal.records.kinds import MEASURED_KIND
from eol_cal.records.rows import parse_record, row_values
from eol_cal.records.tables import baselines, metadata, runs, schema_version

#: the layout this code writes (1: the SQLite table of eol-cal before schema_version)
SCHEMA_VERSION = 5
#: the oldest layout whose ``runs`` columns are those this code reads (readers of runs take it as it is)
RUNS_VERSION = 4
#: PostgreSQL advisory lock: creation, migration and the gate's numbered changes, one at a time
LOCK_ID = 7413001
#: ``runs`` columns added by each version (version: names; their types are the table's)
_RUNS_ADDED = {2: ("station", "operator"), 3: ("limits_json", "error_step", "phase_c6", "fit_r2", "fit_rms_nm"),
               4: ("kind", "causes")}
#: the baselines' own layouts before version 5 (1: without the columns of 2), and the gate's
_BASELINE_LAYOUT, _GATE_LAYOUT = 2, 1


def lock(con: Connection) -> None:
    """Hold the records database's one lock until the transaction ends (PostgreSQL; SQLite's
    ``BEGIN IMMEDIATE`` holds the write lock already)."""
    if con.dialect.name == "postgresql":
        con.execute(sa.text(f"SELECT pg_advisory_xact_lock({LOCK_ID})"))


def version_of(con: Connection) -> int | None:
    """The layout of the database: None when empty, 1 for the table without schema_version."""
    insp = sa.inspect(con)
    if insp.has_table("schema_version"):
        v = con.execute(sa.select(sa.func.max(schema_version.c.version))).scalar()
        return int(v) if v is not None else 1
    return 1 if insp.has_table("runs") else None


def _create(con: Connection) -> None:
    metadata.create_all(con)
    con.execute(schema_version.insert().values(version=SCHEMA_VERSION))


def ensure_schema(con: Connection) -> None:
    """For a writer, inside its transaction: create every table of an empty database; refuse one
    at another version (:class:`SchemaError`)."""
    v = version_of(con)
    if v is None:
        lock(con)  # two stations writing the first record of a new database at once: one creates
        v = version_of(con)
    if v is None:
        _create(con)
    else:
        _refuse_other(v, "writes")


def _refuse_other(v: int, does: str) -> None:
    if v > SCHEMA_VERSION:
        raise SchemaError(f"records database at schema version {v} is newer than this tool ({SCHEMA_VERSION})")
    if v < SCHEMA_VERSION:
        raise SchemaError(f"records database at schema version {v}, this tool {does} version "
                          f"{SCHEMA_VERSION}: migrate it first (eol-cal records migrate)")


def readable(con: Connection) -> bool:
    """For a reader of the baseline or gate tables: False for an empty database (nothing stored
    yet), True at :data:`SCHEMA_VERSION`; :class:`SchemaError` at another version."""
    v = version_of(con)
    if v is not None:
        _refuse_other(v, "reads")
    return v is not None


def migrate(db: str | Path, timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> tuple[int | None, int]:
    """Bring a records database to :data:`SCHEMA_VERSION` (creating it when empty), every table
    in one transaction (the module's docstring lists the steps). A row's corrupt record JSON
    refuses the migration, naming the run; so does a table of a newer layout. Returns ``(version
    before, version now)``; ``before`` is None for a new database."""
    eng = engine(db, timeout_s)
    try:
        with eng.begin() as con:
            lock(con)
            refuse_foreign(con)
            v = version_of(con)
            if v is None:
                _create(con)
                return None, SCHEMA_VERSION
            if v > SCHEMA_VERSION:
                _refuse_other(v, "writes")
            added = [name for step in range(v + 1, SCHEMA_VERSION + 1) for name in _RUNS_ADDED.get(step, ())]
            for name in added:
                con.exec_driver_sql(f"ALTER TABLE runs ADD COLUMN {name} {runs.c[name].type.compile(dialect=con.dialect)}")
            if added:
                _fill(con, db, added)
            if v < 5:
                _own_versions_to_5(con)
            metadata.create_all(con)  # the tables and indexes a database lacks; existing ones are kept
            con.execute(schema_version.delete())
            con.execute(schema_version.insert().values(version=SCHEMA_VERSION))
            return v, SCHEMA_VERSION
    finally:
        dispose(eng, db)


def _own_version(con: Connection, table: str, newest: int) -> int | None:
    """The layout in one of the version tables of before version 5 (None: absent); a newer one refused."""
    if not sa.inspect(con).has_table(table):
        return None
    v = con.exec_driver_sql(f"SELECT max(version) FROM {table}").scalar()
    if v is not None and int(v) > newest:
        raise SchemaError(f"{table} holds layout {v}, newer than this tool ({newest})")
    return None if v is None else int(v)


def _own_versions_to_5(con: Connection) -> None:
    """Step 4 -> 5: the baseline and gate tables' own versions folded into ``schema_version``."""
    if _own_version(con, "baseline_schema_version", _BASELINE_LAYOUT) == 1:
        for name in ("kind", "stations"):
            con.exec_driver_sql(f"ALTER TABLE baselines ADD COLUMN {name} "
                                f"{baselines.c[name].type.compile(dialect=con.dialect)}")
        # a baseline of layout 1 was made of production runs, of its one station or all
        con.execute(baselines.update().values(kind=MEASURED_KIND))
        for name, station in con.execute(sa.select(baselines.c.name, baselines.c.station)).all():
            if station is not None:
                con.execute(baselines.update().where(baselines.c.name == name).values(stations=json.dumps([station])))
    _own_version(con, "gate_schema_version", _GATE_LAYOUT)
    for table in ("baseline_schema_version", "gate_schema_version"):
        if sa.inspect(con).has_table(table):
            con.exec_driver_sql(f"DROP TABLE {table}")


def _fill(con: Connection, db: str | Path, names: list[str], batch: int = 2000) -> None:
    """Fill the ``runs`` columns ``names`` of every row from its record JSON, ``batch`` rows at a
    time (a plant's table of record documents does not fit in memory at once)."""
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
