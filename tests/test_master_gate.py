"""The master-motor gate on loopback simulators (`eol-cal run`, the whole cycle): a production
serial is refused while no master run passed (exit 2, one line, a refusal record, nothing
touched), runs after a passing master run, and is refused again after a failing one; master
runs are recorded as kind master and stay out of the lot's statistics."""

from __future__ import annotations

import json

from click.testing import CliRunner
import pytest

from cli.main import cli
from eol_cal.ecu.flash import active_block_from_file
from eol_cal.schemas import validator
from eol_cal.sim.loopback import loopback_station
from eol_cal.records.query import query_records
from test_station_run import MOTOR, files, run_args  # noqa: F401 - files: the fixture

MASTER = "M-MASTER"
ENV = {"EOL_CAL_STATION_ID": "EOL-7", "EOL_CAL_MASTER_SERIAL": MASTER, "EOL_CAL_MASTER_EVERY_H": "8",
       "EOL_CAL_MASTER_REFERENCE_K6": "0.62", "EOL_CAL_MASTER_TOLERANCE_K6": "0.05"}  # the paper motor: k6 0.62 mN*m/A


def _run(files, tmp_path, serial: str, env: dict, as_json: bool = True):  # noqa: F811
    db = tmp_path / "r.sqlite"
    with loopback_station(serial, 1, tmp_path / "sim", spec_for=lambda req: MOTOR) as st:
        args = run_args(files, st, serial, db, tmp_path / "reports")
        if not as_json:
            args.remove("--json")
        res = CliRunner().invoke(cli, args, env=env)
        return res, st.flash_file


@pytest.mark.slow
def test_master_gate_refuses_then_lets_through_then_refuses_after_a_failed_master(files, tmp_path):  # noqa: F811
    # no master run yet: refused before anything is touched, one line, exit 2
    res, flash = _run(files, tmp_path, "P-1", ENV, as_json=False)
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("P-1: refused, master check due: no run of the master M-MASTER")
    assert "run the master M-MASTER first" in lines[0]
    assert active_block_from_file(flash) is None  # the ECU was never written
    # the master: kind master, judged against its reference too
    res, _ = _run(files, tmp_path, MASTER, ENV)
    assert res.exit_code == 0, res.output
    master = json.loads(res.stdout)["record"]
    assert master["kind"] == "master" and master["verdict"] == "pass"
    # now the production serial runs the whole cycle
    res, _ = _run(files, tmp_path, "P-1", ENV)
    assert res.exit_code in (0, 1), res.output
    prod = json.loads(res.stdout)["record"]
    assert prod["kind"] == "production" and prod["steps"][0]["step"] == "master check"
    # the production run recorded the rules and the master run that admitted it
    assert prod["gate"]["seq"] == 1 and prod["gate"]["master_run"] == master["run_id"]
    assert master["gate"]["checks"][0]["quantity"] == "k6" and master["gate"]["checks"][0]["passed"]
    res = CliRunner().invoke(cli, ["gate", "admitted", "--db", str(tmp_path / "r.sqlite"), "--serial", "P-1", "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["runs"][1]["gate"]["master_run"] == master["run_id"]
    # settings that differ from the database's rules are refused; the rules change by command
    res, _ = _run(files, tmp_path, MASTER, {**ENV, "EOL_CAL_MASTER_REFERENCE_K6": "0.90"})
    assert res.exit_code == 2 and "eol-cal gate set" in res.output
    res = CliRunner().invoke(cli, ["gate", "set", "--db", str(tmp_path / "r.sqlite"), "--station", "EOL-7", "--serial",
                                   MASTER, "--reference", "k6=0.90", "--tolerance", "k6=0.05", "--every-h", "8",
                                   "--by", "qe"])
    assert res.exit_code == 0, res.output
    # a master run outside its tolerance fails, and closes the gate
    env = {k: v for k, v in ENV.items() if not k.startswith("EOL_CAL_MASTER")}  # the database's rules alone
    res, _ = _run(files, tmp_path, MASTER, env)
    assert res.exit_code == 1, res.output
    failed = json.loads(res.stdout)["record"]
    assert failed["kind"] == "master" and failed["verdict"] == "fail"
    assert any(r.startswith("master k6 = 0.6") and "from its reference 0.9 (tolerance +-0.05)" in r
               for r in failed["reasons"])
    res, _ = _run(files, tmp_path, "P-1", env)
    assert res.exit_code == 2
    refused = json.loads(res.stdout)["record"]
    assert refused["kind"] == "refusal" and refused["refusal_codes"] == ["master_failed"]
    for doc in (master, failed, refused):  # the records as the schema says
        validator("run-record").validate(doc)
    assert refused["reasons"][0].startswith("master check: master check failed: the last run of the master M-MASTER")
    # every run recorded, each with its kind; the lot's statistics take the production run alone
    db = tmp_path / "r.sqlite"
    recs = query_records(db, kind="all")
    assert [(r.serial, r.kind, r.verdict) for r in recs] == [
        ("P-1", "refusal", "error"), (MASTER, "master", "pass"), ("P-1", "production", prod["verdict"]),
        (MASTER, "refusal", "error"), (MASTER, "master", "fail"), ("P-1", "refusal", "error")]
    assert [r.refusal_codes for r in recs if r.kind == "refusal"] == [("master_due",), ("settings",), ("master_failed",)]
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(db), "--json", "--min-n", "2"])
    doc = json.loads(res.stdout)
    assert doc["runs"] == 1 and doc["motors"] == 1 and doc["refusals"]["runs"] == 3
    # the type-1 study of the master takes its master runs
    res = CliRunner().invoke(cli, ["msa", "type1", "--db", str(db), "--serial", MASTER, "--json"])
    assert json.loads(res.stdout)["runs"] == 2


@pytest.mark.slow
def test_the_operator_station_refuses_until_the_master_passed(tmp_path):
    """`eol-cal station --demo` on a pseudo-terminal with a [master] table in its settings: a
    production serial gets one line, the master runs, then the same serial runs."""
    import sqlite3

    from eol_cal.sim.loopback import demo_motor_spec
    from eol_cal.station.operator_session import demo_seed
    from test_station_operator import MOTOR_S, PASSING, Terminal

    master, serial = PASSING
    k6 = demo_motor_spec(demo_seed(master), master).k6 * 1e3
    settings = tmp_path / "station.toml"
    settings.write_text(f'[master]\nserial = "{master}"\nshifts = "06:00,14:00,22:00"\ntimezone = "Europe/Berlin"\n'
                        f"[master.reference]\nk6 = {k6:.4f}\n[master.tolerance]\nk6 = 0.05\n")
    out = tmp_path / "session"
    t = Terminal(["station", "--demo", "--station", str(settings), "--out", str(out), "--operator", "ann"], tmp_path)
    try:
        t.expect(rf"master {master} \(per shift \(Europe/Berlin\)\): master check due: no run of the master {master}", 60)
        t.expect(r"Scan serial", 30)
        t.type(serial)
        t.expect(rf"{serial}: refused, master check due: no run of the master {master} recorded; run the master "
                 rf"{master} first \(record [0-9a-f]{{8}}; nothing was touched\)", 60)
        t.expect(r"Scan serial", 10)
        t.type(master)
        t.expect(rf"{master}: PASS", MOTOR_S)
        t.expect(r"Scan serial", 10)
        t.type(serial)
        t.expect(rf"{serial}: PASS", MOTOR_S)
        t.expect(r"Scan serial", 10)
        t.type("")
        assert t.exit_code() == 0, t.text[-3000:]
    finally:
        t.close()
    with sqlite3.connect(out / "results.sqlite") as con:
        rows = con.execute("SELECT serial, kind, verdict FROM runs ORDER BY started_at").fetchall()
    assert rows == [(serial, "refusal", "error"), (master, "master", "pass"), (serial, "production", "pass")]
