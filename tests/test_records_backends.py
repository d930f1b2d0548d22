"""The same records suite on both backends: SQLite (a file) and PostgreSQL (a real server).

Idempotent insert, query filters, concurrent writers (no record lost or duplicated), an outage
that spools and a flush into the same backend, and the migration of a version-1 database
written with the schema of eol-cal before ``schema_version``.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import sqlalchemy as sa

from eol_cal.sim.run_records import make_record, v1_record
from eol_cal.records.record import RunRecord
from eol_cal.records.connect import SchemaError, db_key, engine
from eol_cal.records.migrations import SCHEMA_VERSION, migrate
from eol_cal.records.write import insert_records
from eol_cal.records.query import query_records, read_rows, select_runs
from eol_cal.records.spool import flush_spool, save_record


def record(serial: str = "M-1", verdict: str = "pass", started: str = "2026-11-22T10:00:00.000+00:00",
           k6: float = 1.0e-3, station: str = "EOL-1") -> RunRecord:
    # a failed run: k6 over the variant's limit (1.2 mN*m/A)
    return make_record(serial, started=started, k6=k6 if verdict == "pass" else max(k6, 1.3e-3), station=station,
                       operator="ab")


def test_insert_is_idempotent_and_columns_are_queryable(records_db):
    recs = [record("A", started="2026-11-21T10:00:00.000+00:00"), record("B", "fail", k6=3e-3, station="EOL-2")]
    assert insert_records(records_db, recs) == 2
    assert insert_records(records_db, recs) == 0  # same run ids: nothing twice
    assert [r.run_id for r in query_records(records_db)] == [r.run_id for r in recs]
    rows = read_rows(records_db, select_runs(station="EOL-2"))
    assert len(rows) == 1 and rows[0]["serial"] == "B" and rows[0]["k6"] == 3e-3 and rows[0]["operator"] == "ab"
    assert rows[0]["variant"] == "EPS-STD" and json.loads(rows[0]["record_json"]) == recs[1].to_json()
    assert rows[0]["kind"] == "production" and json.loads(rows[0]["causes"]) == ["max_k6"]
    assert [r["serial"] for r in read_rows(records_db, select_runs(since="2026-11-22"))] == ["B"]
    assert [r["serial"] for r in read_rows(records_db, select_runs(until="2026-11-21"))] == ["A"]
    assert query_records(records_db, serial="A")[0] == recs[0]


@pytest.mark.slow
def test_concurrent_writers_lose_and_duplicate_nothing(records_db):
    insert_records(records_db, [])  # create the schema once, as `records migrate` would
    batches = [[record(f"W{w}-{i}") for i in range(25)] for w in range(4)]

    def insert(r: RunRecord) -> int:
        # the lock wait is not what this test checks: 200 transactions of four threads on a loaded
        # machine (load 9 on 2 cores) waited past the station's 5 s for SQLite's lock
        return insert_records(records_db, [r], timeout_s=60.0)

    def write(batch: list[RunRecord]) -> int:
        # one record per transaction, each written twice (a retried flush)
        return sum(insert(r) + insert(r) for r in batch)

    with ThreadPoolExecutor(4) as pool:
        assert sum(pool.map(write, batches)) == 100
    ids = [r.run_id for r in query_records(records_db)]
    assert len(ids) == len(set(ids)) == 100
    assert set(ids) == {r.run_id for b in batches for r in b}


def _down(db) -> str | Path:
    """The same backend, unreachable: a missing directory, or a port nobody listens on."""
    if isinstance(db, Path):
        return db.parent / "unmounted" / db.name
    url = sa.engine.make_url(db)
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return url.set(port=port).render_as_string(hide_password=False)


def test_outage_spools_and_the_flush_writes_it_once(records_db, tmp_path: Path):
    down = _down(records_db)
    spool = tmp_path / "spool"
    r = record("S")
    res = save_record(r, down, spool, timeout_s=1.0)
    assert res.where == "spool" and Path(res.path).is_file()
    assert flush_spool(down, spool, timeout_s=1.0).remaining == 1  # still down: nothing removed
    # the service is back (the same target): the flush writes it, a second flush has nothing left
    if isinstance(records_db, Path):
        (tmp_path / "unmounted").mkdir()
        target = down
    else:
        doc = json.loads(Path(res.path).read_text())
        insert_records(records_db, [r])  # an interrupted earlier flush had inserted it already
        target = records_db
        doc["db"] = db_key(records_db)  # spooled while the server was down, flushed when it is back
        Path(res.path).write_text(json.dumps(doc))
    out = flush_spool(target, spool)
    assert out.flushed_files == 1 and out.remaining == 0 and out.error is None
    assert [x.run_id for x in query_records(target)] == [r.run_id]
    assert flush_spool(target, spool).flushed_files == 0


# the table of eol-cal before schema_version (version 1), as that code created it
_V1 = """CREATE TABLE runs (run_id TEXT PRIMARY KEY, serial TEXT NOT NULL, variant TEXT, started_at TEXT NOT NULL,
ended_at TEXT, verdict TEXT NOT NULL CHECK (verdict IN ('pass', 'fail', 'error')), reasons TEXT NOT NULL, k6 REAL,
phase_k6 REAL, c6 REAL, pp_before_pct REAL, pp_after_pct REAL, improvement_pct REAL, capture_before TEXT,
sha256_before TEXT, capture_after TEXT, sha256_after TEXT, fit_json TEXT, block_crc32 TEXT, block_sequence INTEGER,
tool_version TEXT, layout_version INTEGER, report_dir TEXT, record_json TEXT NOT NULL);
CREATE INDEX runs_serial ON runs (serial); CREATE INDEX runs_started ON runs (started_at);"""


def test_migrate_a_version_1_database(records_db):
    old = [v1_record("A", started="2026-11-21T10:00:00.000+00:00"), v1_record("B", station="EOL-7")]
    eng = engine(records_db)
    with eng.begin() as con:
        for stmt in _V1.split(";"):
            if stmt.strip():
                con.exec_driver_sql(stmt)
        for r in old:
            con.execute(sa.text("INSERT INTO runs (run_id, serial, started_at, verdict, reasons, k6, record_json) "
                                "VALUES (:i, :s, :t, :v, '[]', :k, :j)"),
                        dict(i=r["run_id"], s=r["serial"], t=r["started_at"], v=r["verdict"],
                             k=r["fit"]["k6"]["value"], j=json.dumps(r)))
    if isinstance(records_db, Path):
        eng.dispose()
    assert [r.kind for r in query_records(records_db)] == ["production"] * 2  # an old database reads
    with pytest.raises(SchemaError, match="version 1"):
        insert_records(records_db, [record("X")])
    assert migrate(records_db) == (1, SCHEMA_VERSION)
    assert migrate(records_db) == (SCHEMA_VERSION, SCHEMA_VERSION)
    assert insert_records(records_db, [record("C", started="2026-11-23T10:00:00.000+00:00")]) == 1
    rows = read_rows(records_db, select_runs(station="EOL-7"))
    assert [r["serial"] for r in rows] == ["B"] and rows[0]["operator"] == "ab"
    assert [r.serial for r in query_records(records_db)] == ["A", "B", "C"]


def test_migrate_creates_a_new_database(records_db):
    assert migrate(records_db) == (None, SCHEMA_VERSION)
    assert query_records(records_db) == []


def test_records_cli_migrate_and_query(records_db):
    from click.testing import CliRunner

    from cli.main import cli

    runner = CliRunner()
    res = runner.invoke(cli, ["records", "migrate", "--db", str(records_db)])
    assert res.exit_code == 0 and f"created schema version {SCHEMA_VERSION}" in res.output, res.output
    insert_records(records_db, [record("A"), record("B", "fail")])
    res = runner.invoke(cli, ["records", "--db", str(records_db), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["summary"]["runs"] == 2
    res = runner.invoke(cli, ["records", "migrate", "--db", str(records_db)])
    assert res.exit_code == 0 and "already at" in res.output
