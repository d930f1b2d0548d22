"""Run records: SQLite in WAL mode, and no record lost when the database is locked or missing.

Real SQLite files; the lock is an exclusive transaction held by a second connection.
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.errors import InputError
from eol_cal.records.record import RunRecord
from eol_cal.records.connect import RecordError
from eol_cal.records.tables import COLUMN_NAMES
from eol_cal.records.write import insert_records
from eol_cal.records.query import query_records, summarise
from eol_cal.records.spool import flush_spool, save_record


def record(serial: str = "M-1", verdict: str = "pass", started: str = "2026-11-22T10:00:00.000+00:00",
           k6: float = 1.0e-3, before: float = 3.0, after: float = 0.5) -> RunRecord:
    """A production run that passes, fails (k6 or p-p past the demo variant's limits) or errs in its acquisition."""
    if verdict == "error":
        return make_record(serial, started=started, error_step="acquire")
    if verdict == "fail" and k6 <= 1.2e-3 and after <= 2.0:
        k6 = 3e-3
    return make_record(serial, started=started, k6=k6, pp_before=before, pp_after=after)


def rows(db: Path) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        return con.execute("SELECT run_id, serial, verdict, k6, block_crc32, block_sequence, sha256_before FROM runs").fetchall()
    finally:
        con.close()


def test_database_is_wal_and_holds_every_column(tmp_path: Path):
    db = tmp_path / "results.sqlite"
    r = record()
    res = save_record(r, db, tmp_path / "spool")
    assert res.where == "db"
    con = sqlite3.connect(db)
    try:
        assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        cols = [c[1] for c in con.execute("PRAGMA table_info(runs)")]
        row = con.execute("SELECT * FROM runs").fetchone()
    finally:
        con.close()
    assert tuple(cols) == COLUMN_NAMES
    values = dict(zip(cols, row, strict=True))
    cal = r.block("calibrated")
    assert values["run_id"] == r.run_id and values["verdict"] == "pass" and values["variant"] == "EPS-STD"
    assert values["block_crc32"] == cal.crc32 and values["block_sequence"] == cal.sequence == 2
    assert values["sha256_before"] == r.captures["before"].sha256 and values["capture_after"] == r.captures["after"].path
    assert json.loads(values["fit_json"])["k6"]["value"] == 1.0e-3
    assert json.loads(values["record_json"]) == r.to_json()
    assert values["kind"] == "production" and json.loads(values["causes"]) == []
    assert not (tmp_path / "spool").exists()


def test_locked_database_spools_then_flush_writes_it(tmp_path: Path):
    db = tmp_path / "results.sqlite"
    spool = tmp_path / "spool"
    first = record("M-1")
    save_record(first, db, spool)
    holder = sqlite3.connect(db, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")  # another station process holds the write lock
    try:
        r = record("M-2")
        res = save_record(r, db, spool, timeout_s=0.2)
        assert res.where == "spool"
        assert "locked" in res.why
        spooled = json.loads(Path(res.path).read_text())
        assert spooled["record"] == r.to_json() and spooled["db"] == str(db.resolve())
        # still locked: a flush keeps the file and says why
        fl = flush_spool(db, spool, timeout_s=0.2)
        assert fl.flushed_files == 0 and fl.remaining == 1 and "locked" in fl.error
        assert Path(res.path).exists()
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    fl = flush_spool(db, spool)
    assert (fl.inserted, fl.flushed_files, fl.remaining) == (1, 1, 0)
    assert list(spool.glob("*.json")) == []
    assert sorted(x[1] for x in rows(db)) == ["M-1", "M-2"]


def test_missing_directory_spools_then_flush_after_it_is_back(tmp_path: Path):
    db = tmp_path / "share" / "results.sqlite"  # the share is not mounted
    spool = tmp_path / "spool"
    recs = [record(f"M-{i}") for i in range(3)]
    for r in recs:
        res = save_record(r, db, spool)
        assert res.where == "spool" and "does not exist" in res.why
    assert not db.parent.exists()  # nothing created where the share should be
    assert len(list(spool.glob("*.json"))) == 3
    db.parent.mkdir()
    fl = flush_spool(db, spool)
    assert fl.inserted == 3 and fl.remaining == 0
    assert {x[0] for x in rows(db)} == {r.run_id for r in recs}


def test_flush_is_idempotent_and_leaves_other_databases_records(tmp_path: Path):
    db, other = tmp_path / "a.sqlite", tmp_path / "missing" / "b.sqlite"
    spool = tmp_path / "spool"
    r = record()
    other_file = Path(save_record(record("B-1"), other, spool).path)  # spooled for another database
    path = Path(save_record(r, db.parent / "nodir" / "x.sqlite", spool).path)
    assert path.exists()
    # the same record inserted, then its spool file found again (crash between insert and unlink)
    insert_records(db, [r])
    doc = json.loads(path.read_text())
    doc["db"] = str(db.resolve())
    path.write_text(json.dumps(doc))
    fl = flush_spool(db, spool)
    assert fl.flushed_files == 1 and fl.inserted == 0 and fl.other_db == 1
    assert len(rows(db)) == 1
    assert other_file.exists() and not path.exists()
    # a stray file in the spool is reported and left alone; it does not stop the flush
    stray = spool / "notes.json"
    stray.write_text("{not json")
    r2 = record("M-9")
    save_record(r2, db.parent / "nodir" / "x.sqlite", spool)
    doc = json.loads((spool / f"{r2.run_id}.json").read_text())
    doc["db"] = str(db.resolve())
    (spool / f"{r2.run_id}.json").write_text(json.dumps(doc))
    fl = flush_spool(db, spool)
    assert fl.inserted == 1 and len(fl.bad_files) == 1 and "notes.json" in fl.bad_files[0]
    assert stray.exists()


def test_no_spool_either_is_an_error_naming_both(tmp_path: Path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(RecordError, match="database .*spool"):
        save_record(record(), tmp_path / "nodir" / "r.sqlite", blocker / "spool")


def test_query_by_serial_and_day_and_pass_rate(tmp_path: Path):
    db = tmp_path / "r.sqlite"
    recs = [
        record("A", "pass", "2026-11-21T23:59:00.000+00:00"),
        record("B", "fail", "2026-11-22T08:00:00.000+00:00", k6=3e-3),
        record("A", "pass", "2026-11-22T09:00:00.000+00:00"),
        record("C", "error", "2026-11-22T10:00:00.000+00:00"),
    ]
    insert_records(db, recs)
    assert [r.serial for r in query_records(db)] == ["A", "B", "A", "C"]
    assert [r.run_id for r in query_records(db, serial="A")] == [recs[0].run_id, recs[2].run_id]
    assert [r.serial for r in query_records(db, day="2026-11-22")] == ["B", "A", "C"]
    s = summarise(query_records(db, day="2026-11-22"))
    assert (s["runs"], s["pass"], s["fail"], s["error"]) == (3, 1, 1, 1)
    assert s["pass_rate"] == 0.5 and s["motors"] == 3 and s["motors_pass"] == 1
    with pytest.raises(InputError, match="database not found"):
        query_records(tmp_path / "none.sqlite")


def test_records_cli_flush_json_and_plot(tmp_path: Path):
    db = tmp_path / "r.sqlite"
    spool = tmp_path / "spool"
    insert_records(db, [record("A", "pass", "2026-11-22T09:00:00.000+00:00")])
    holder = sqlite3.connect(db, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")
    try:
        saved = save_record(record("B", "fail", "2026-11-22T10:00:00.000+00:00", after=4.0), db, spool, timeout_s=0.1)
        assert saved.where == "spool"
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    runner = CliRunner()
    res = runner.invoke(cli, ["records", "--db", str(db), "--flush", "--spool-dir", str(spool), "--json",
                              "--plot", str(tmp_path / "lot.png")])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["schema"] == "eol-cal/records/2"
    assert doc["summary"]["runs"] == 2 and doc["summary"]["pass_rate"] == 0.5
    assert [r["serial"] for r in doc["records"]] == ["A", "B"]
    assert (tmp_path / "lot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    res = runner.invoke(cli, ["records", "--db", str(db), "--serial", "B"])
    assert res.exit_code == 0 and "pass rate 0.0 %" in res.output
    res = runner.invoke(cli, ["records", "--db", str(db), "--day", "22-11-2026"])
    assert res.exit_code == 2 and "YYYY-MM-DD" in res.output
    res = runner.invoke(cli, ["records", "--db", str(tmp_path / "x.sqlite")])
    assert res.exit_code == 2 and "database not found" in res.output


def test_a_spooled_record_that_does_not_read_is_left_alone_not_lost(tmp_path: Path):
    db, spool = tmp_path / "r.sqlite", tmp_path / "spool"
    path = Path(save_record(record("M-5"), tmp_path / "nodir" / "r.sqlite", spool).path)
    doc = json.loads(path.read_text())
    doc["db"] = str(db.resolve())
    doc["record"]["fit"]["k6"]["value"] = "big"  # damaged on the station's disk
    path.write_text(json.dumps(doc))
    fl = flush_spool(db, spool)
    assert fl.inserted == 0 and len(fl.bad_files) == 1 and "fit.k6.value" in fl.bad_files[0] and path.exists()
