"""The master gate as a record (issue 36, class 2): the rules live in the records database per
station (`eol-cal gate set/clear/show/history`, each change a row, every value checked as a
setting, stored rows checked as input), the station's own latest master run counts, by instant,
not after the station's clock, judged under the rules in force; `eol-cal run` under a station id
with rules cannot leave them out. On SQLite and PostgreSQL (``records_db``)."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
from pathlib import Path

import pytest
import sqlalchemy as sa
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.msa.gate import Gate, MasterGateClosed, check_gate, gate_in_force
from eol_cal.msa.master import MasterRun, master_due, master_settings
from eol_cal.msa.rules import change, current, history
from eol_cal.records.record import GateInfo, MasterCheck
from eol_cal.schemas import SCHEMA_FILES, validator
from eol_cal.records.connect import engine
from eol_cal.records.write import insert_records

NOW = dt.datetime(2026, 11, 22, 12, 0, tzinfo=dt.UTC)
RULES = {"master.serial": "M-MASTER", "master.reference.k6": 0.62, "master.tolerance.k6": 0.05, "master.every_h": 8.0}
MASTER = master_settings(RULES, "test")
assert MASTER is not None


def _set(db, *extra: str, station: str = "EOL-1"):
    return CliRunner().invoke(cli, ["gate", "set", "--db", str(db), "--station", station, "--serial", "M-MASTER",
                                    "--reference", "k6=0.62", "--tolerance", "k6=0.05", "--by", "qe", *extra])


def _master_run(started: str, seq: int | None, *, passed: bool = True, station: str | None = "EOL-1"):
    rec = make_record("M-MASTER", started=started, station=station, kind="master", pp_after=None if passed else 50.0)
    check = MasterCheck("k6", "mN*m/A", 0.63, 0.62, 0.05, 0.01, True)
    gate = GateInfo({"serial": "M-MASTER", "reference": {"k6": 0.62}, "tolerance": {"k6": 0.05}, "every_h": 8.0,
                     "shifts": None, "timezone": "UTC"}, "records database", station, seq, started, checks=(check,))
    return dataclasses.replace(rec, gate=gate)


def test_gate_rules_are_set_changed_and_cleared_by_command_each_change_a_row(records_db):
    res = _set(records_db, "--every-h", "8", "--note", "first rules")
    assert res.exit_code == 0, res.output
    assert _set(records_db, "--every-h", "4").exit_code == 0
    res = CliRunner().invoke(cli, ["gate", "show", "--db", str(records_db), "--station", "EOL-1", "--json"])
    (shown,) = json.loads(res.stdout)["changes"]
    assert res.exit_code == 0 and shown["seq"] == 2 and shown["rules"]["every_h"] == 4.0 and shown["set_by"] == "qe"
    assert CliRunner().invoke(cli, ["gate", "clear", "--db", str(records_db), "--station", "EOL-1",
                                    "--by", "qe"]).exit_code == 2  # a clear says why
    res = CliRunner().invoke(cli, ["gate", "clear", "--db", str(records_db), "--station", "EOL-1", "--by", "qe",
                                   "--note", "line stopped"])
    assert res.exit_code == 0, res.output
    changes = history(records_db, "EOL-1")
    assert [(c.seq, c.master is not None) for c in changes] == [(1, True), (2, True), (3, False)]
    assert changes[0].note == "first rules" and changes[0].master == MASTER
    assert CliRunner().invoke(cli, ["gate", "show", "--db", str(records_db), "--station", "EOL-1"]).exit_code == 1
    assert current(records_db, "EOL-2") is None  # another station has no rules
    # every --json document of the gate's commands as its schema says
    for args in (["show", "--station", "EOL-1"], ["history"], ["admitted", "--serial", "M-MASTER"],
                 ["clear", "--station", "EOL-2", "--by", "qe", "--note", "n"],
                 ["set", "--station", "EOL-2", "--serial", "M-2", "--reference", "phase_k6=10", "--tolerance",
                  "phase_k6=2", "--shifts", "06:00,14:00", "--timezone", "Europe/Berlin", "--by", "qe"]):
        res = CliRunner().invoke(cli, ["gate", args[0], "--db", str(records_db), *args[1:], "--json"])
        doc = json.loads(res.stdout)
        validator(SCHEMA_FILES[doc["schema"]]).validate(doc)


@pytest.mark.parametrize("extra", [
    ("--every-h", "nan"), ("--every-h", "0"), ("--every-h", "1e9"), ("--shifts", "25:00"),
    ("--every-h", "8", "--shifts", "06:00"),
    ("--every-h", "8", "--timezone", "Mars/Olympus"), ("--every-h", "8", "--tolerance", "c6=0.1"),
    ("--every-h", "8", "--reference", "k6=-1"),
    ("--every-h", "8", "--reference", "phase_k6=10", "--tolerance", "phase_k6=200"),
    ("--every-h", "8", "--reference", "volts=3"), ("--every-h", "8", "--tolerance", "k6=-0.05"),
])
def test_every_rule_value_is_checked_like_a_setting(tmp_path, extra):
    db = tmp_path / "r.sqlite"
    res = _set(db, *extra)
    assert res.exit_code == 2 and res.output.startswith("error:") and "Traceback" not in res.output, res.output
    assert not db.exists() or current(db, "EOL-1") is None  # nothing recorded


def test_a_bad_serial_or_station_is_refused(tmp_path):
    db = tmp_path / "r.sqlite"
    for args in (["--serial", ""], ["--serial", "M\x00"], ["--serial", "X" * 40]):
        res = CliRunner().invoke(cli, ["gate", "set", "--db", str(db), "--station", "EOL-1", *args, "--reference",
                                       "k6=0.6", "--tolerance", "k6=0.1", "--every-h", "8", "--by", "qe"])
        assert res.exit_code == 2, res.output
    res = _set(db, "--every-h", "8", station=" ")
    assert res.exit_code == 2 and "station" in res.output


@pytest.mark.parametrize(("column", "value", "named"), [
    ("rules_json", '{"serial": "M-MASTER", "reference": {"k6": 0.62}, "tolerance": {"k6": 0}, "every_h": 8,'
                   ' "shifts": null, "timezone": "UTC"}', "master.tolerance.k6"),
    ("rules_json", '{"serial": "M-MASTER", "reference": {"k6": "x"}, "tolerance": {"k6": 0.05}, "every_h": 8,'
                   ' "shifts": null, "timezone": "UTC"}', "master.reference.k6"),
    ("rules_json", "not json", "rules_json"),
    ("set_at", "yesterday", "set_at"),
])
def test_a_stored_rules_row_is_checked_as_input_and_closes_the_gate(records_db, column, value, named):
    assert _set(records_db, "--every-h", "8").exit_code == 0
    eng = engine(records_db)
    with eng.begin() as con:
        con.execute(sa.text(f"UPDATE gate_rules SET {column} = :v"), {"v": value})
    eng.dispose()
    with pytest.raises(MasterGateClosed) as info:
        gate_in_force(records_db, "EOL-1", None)
    assert "gate_rules row 'EOL-1' #1" in str(info.value) and named in str(info.value)
    res = CliRunner().invoke(cli, ["gate", "show", "--db", str(records_db), "--station", "EOL-1"])
    assert res.exit_code == 2 and "Traceback" not in res.output


def test_a_newer_layout_is_refused_by_the_gate(records_db):
    assert _set(records_db, "--every-h", "8").exit_code == 0
    eng = engine(records_db)
    with eng.begin() as con:
        con.execute(sa.text("UPDATE schema_version SET version = 99"))
    eng.dispose()
    res = CliRunner().invoke(cli, ["gate", "history", "--db", str(records_db)])
    assert res.exit_code == 2 and "schema version 99 is newer than this tool" in res.output


def test_settings_rules_are_recorded_once_and_differing_ones_refused(tmp_path):
    db = tmp_path / "r.sqlite"
    gate = gate_in_force(db, "EOL-1", MASTER)
    assert gate is not None and gate.change is not None and gate.change.seq == 1
    assert gate_in_force(db, "EOL-1", MASTER).change.seq == 1  # the same rules: no new change
    other = dataclasses.replace(MASTER, every_h=1.0)
    with pytest.raises(Exception, match="records database holds other rules for station EOL-1"):
        gate_in_force(db, "EOL-1", other)
    assert gate_in_force(db, "EOL-1", None).master == MASTER  # without settings: the database's rules


def test_the_master_run_is_chosen_by_instant_on_its_own_station_under_the_rules_in_force(records_db):
    change(records_db, "EOL-1", MASTER, "qe")
    gate = gate_in_force(records_db, "EOL-1", None)
    assert gate is not None
    # text order puts the failing run last (11:30 > 10:00), but it started at 09:30 UTC
    passing = _master_run("2026-11-22T10:00:00.000+00:00", 1)
    failing = _master_run("2026-11-22T11:30:00.000+02:00", 1, passed=False)
    assert failing.verdict == "fail"
    insert_records(records_db, [failing, passing])
    last = check_gate(records_db, gate, "EOL-1", now=NOW)
    assert last is not None and last.run_id == passing.run_id and last.checks[0].reference == 0.62
    # another station's master run does not count, nor one of a station without an id
    with pytest.raises(MasterGateClosed, match="no run of the master"):
        check_gate(records_db, Gate(MASTER, None), "EOL-10", now=NOW)
    with pytest.raises(MasterGateClosed, match="no run of the master"):
        check_gate(records_db, Gate(MASTER, None), None, now=NOW)
    # a passing master run dated after the station's clock does not open the gate
    insert_records(records_db, [_master_run("2026-11-22T12:30:00.000+00:00", 1, passed=False),
                                _master_run("2026-11-22T11:00:00.000+00:00", 1, passed=False)])
    with pytest.raises(MasterGateClosed, match="must be followed by a passing one"):
        check_gate(records_db, gate, "EOL-1", now=NOW)
    insert_records(records_db, [_master_run("2026-11-22T13:00:00.000+00:00", 1)])
    with pytest.raises(MasterGateClosed, match="must be followed by a passing one"):
        check_gate(records_db, gate, "EOL-1", now=NOW)
    assert check_gate(records_db, gate, "EOL-1", now=NOW + dt.timedelta(hours=1.5)).passed


def test_a_master_run_under_other_rules_does_not_open_the_gate(records_db):
    change(records_db, "EOL-1", MASTER, "qe")
    insert_records(records_db, [_master_run("2026-11-22T10:00:00.000+00:00", 1)])
    assert check_gate(records_db, gate_in_force(records_db, "EOL-1", None), "EOL-1", now=NOW).passed
    change(records_db, "EOL-1", dataclasses.replace(MASTER, every_h=4.0), "qe")
    with pytest.raises(MasterGateClosed, match=r"was judged against rules #1, the station's rules #2 of EOL-1"):
        check_gate(records_db, gate_in_force(records_db, "EOL-1", None), "EOL-1", now=NOW)
    insert_records(records_db, [_master_run("2026-11-22T09:00:00.000+00:00", None)])  # no gate recorded: older


def test_the_age_of_the_last_master_run_is_never_rounded_away():
    m = dataclasses.replace(MASTER, every_h=0.02)
    last = MasterRun(NOW, True)
    why = master_due(NOW + dt.timedelta(seconds=90), last, m)
    assert why is not None and "was 1.5 min ago" in why and "every 1.2 min" in why and "0.0 h" not in why
    why = master_due(NOW + dt.timedelta(hours=9), last, dataclasses.replace(MASTER, every_h=8.0))
    assert why is not None and "was 9.0 h ago" in why


def test_run_without_the_settings_file_cannot_skip_the_stations_gate(tmp_path):
    """Today `eol-cal run` under the station id, without the settings that held [master], ran
    pre-flight and report only: no master check. Now the database's rules refuse it first."""
    from eol_cal.ecu import protocol as P

    fixtures = Path(__file__).resolve().parent.parent / "fixtures"
    db = tmp_path / "r.sqlite"
    key = tmp_path / "key.hex"
    key.write_text(P.DEV_SECRET.hex())
    assert _set(db, "--every-h", "8").exit_code == 0
    res = CliRunner().invoke(cli, ["run", "--station-id", "EOL-1", "--dyno", "127.0.0.1:1", "--interface", "virtual",
                                   "--channel", "gate-test", "--limits", str(fixtures / "limits.toml"), "--db", str(db),
                                   "--serial", "P-1", "--key-file", str(key), "--report-dir", str(tmp_path / "rep"),
                                   "--spool-dir", str(tmp_path / "spool"), "--json"])
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    assert rec["kind"] == "refusal" and rec["refusal_codes"] == ["master_due"]
    assert [s["step"] for s in rec["steps"]][0] == "master check"
    assert rec["gate"]["seq"] == 1 and rec["gate"]["rules"]["serial"] == "M-MASTER" and rec["gate"]["master_run"] is None


def test_a_failed_master_runs_report_shows_the_failed_check_beside_its_limits(tmp_path):
    """A failed master's report showed every limit PASS under a FAIL verdict; now its checks
    against the references are on it, the failing one FAIL."""
    from eol_cal.report.motor_page import render_motor_report

    rec = _master_run("2026-11-22T10:00:00.000+00:00", 1)
    bad = MasterCheck("k6", "mN*m/A", 0.63, 0.90, 0.05, -0.27, False)
    rec = dataclasses.replace(rec, verdict="fail", reasons=(str(bad.reason),),
                              gate=dataclasses.replace(rec.gate, checks=(bad,)))
    html = render_motor_report(rec, [])
    assert 'id="master-checks"' in html and html.count('class="master-check-row"') == 1
    row = html[html.index('class="master-check-row"'):]
    assert "0.9" in row[:400] and "status-FAIL" in row[:600]
    assert "rules #1 of station EOL-1" in html
