"""The master gate read from a records database (:func:`eol_cal.msa.gate.check_gate`): no master
run, a passing one within its period, a failing one, one past its period, another station's, and
a database that cannot be read. In-process on SQLite: the fast loop's test of the gate (the
whole-cycle tests are in test_master_gate.py)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest

from eol_cal.sim.run_records import make_record
from eol_cal.msa.gate import MasterGateClosed, check_gate, gate_refusal
from eol_cal.msa.master import MasterSettings
from eol_cal.records.write import insert_records

MASTER = MasterSettings("M-MASTER", {"k6": 0.62}, {"k6": 0.05}, every_h=8.0)
NOW = dt.datetime(2026, 11, 22, 12, 0, tzinfo=dt.UTC)


def _master(started: str, *, passed: bool, station: str = "EOL-1"):
    # a passing master run: the template's values; a failing one: its compensated ripple over the limit
    return make_record(MASTER.serial, started=started, station=station, kind="master",
                       pp_after=None if passed else 50.0)


def _closed(db: Path, station: str = "EOL-1", now: dt.datetime = NOW) -> MasterGateClosed:
    with pytest.raises(MasterGateClosed) as info:
        check_gate(db, MASTER, station, now=now)
    return info.value


def test_no_database_and_no_master_run_refuse_production(tmp_path: Path):
    db = tmp_path / "r.sqlite"
    assert "no run of the master M-MASTER recorded" in str(_closed(db))
    insert_records(db, [make_record("S-1", started="2026-11-22T11:00:00.000+00:00")])  # production only
    exc = _closed(db)
    assert exc.problems[0].code == "master_due" and "run the master M-MASTER first" in str(exc)


def test_a_passing_master_run_opens_the_gate_for_its_period_on_its_station(tmp_path: Path):
    db = tmp_path / "r.sqlite"
    insert_records(db, [_master("2026-11-22T09:00:00.000+00:00", passed=True)])
    last = check_gate(db, MASTER, "EOL-1", now=NOW)
    assert last is not None and last.passed and last.started_at == dt.datetime(2026, 11, 22, 9, tzinfo=dt.UTC)
    assert "was 9.0 h ago" in str(_closed(db, now=NOW + dt.timedelta(hours=6)))  # past every_h = 8
    assert _closed(db, station="EOL-2").problems[0].code == "master_due"  # another station's master run


def test_the_latest_master_run_decides_and_a_failed_one_closes_the_gate(tmp_path: Path):
    db = tmp_path / "r.sqlite"
    fail = _master("2026-11-22T10:00:00.000+00:00", passed=False)
    assert fail.verdict == "fail"
    insert_records(db, [_master("2026-11-22T09:00:00.000+00:00", passed=True), fail])
    exc = _closed(db)
    assert exc.problems[0].code == "master_failed" and "must be followed by a passing one" in str(exc)
    insert_records(db, [_master("2026-11-22T11:00:00.000+00:00", passed=True)])
    assert check_gate(db, MASTER, "EOL-1", now=NOW).passed


def test_a_database_that_cannot_be_read_refuses_and_says_so(tmp_path: Path):
    db = tmp_path / "r.sqlite"
    db.write_bytes(b"not a database" * 100)
    exc = _closed(db)
    assert exc.problems[0].code == "master_due" and "cannot read the gate rules: file is not a database" in str(exc)


def test_gate_refusal_is_one_line_for_a_gate_refusal_only():
    refused = make_record("S-9", refused=("master_due",))
    line = gate_refusal(refused)
    assert line is not None and line.startswith("S-9: refused") and "nothing was touched" in line
    assert gate_refusal(make_record("S-9", refused=("wrong_serial",))) is None
    assert gate_refusal(make_record("S-9")) is None
