"""The typed run record: its JSON round trip, the records of the previous schema (real ones, written
by eol-cal before RunRecord: a demo run, a wrong-serial refusal, an early record, a version-3
database), refusals of malformed records, and the library's one spelling of each limit key."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.schemas import validator
from eol_cal.records.limits import LIMIT_KEYS
from eol_cal.records.record import RecordFormatError, RunRecord, record_kind

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "fixtures"


def _doc(name: str) -> dict:
    return json.loads((FIXTURES / name).read_text())


def test_the_round_trip_is_exact():
    doc = _doc("run_record_demo.json")  # a real demo run of this version
    rec = RunRecord.from_json(doc, "run_record_demo.json")
    assert rec.to_json() == doc
    assert json.dumps(RunRecord.from_json(json.loads(json.dumps(rec.to_json()))).to_json()) == json.dumps(doc)
    assert rec.kind == "production" and rec.verdict == "pass" and [b.role for b in rec.blocks] == ["prepare", "calibrated"]
    assert all(c.passed for c in rec.checks) and rec.causes() == []


@pytest.mark.parametrize(("name", "kind", "verdict", "causes"), [
    ("run_record_v1_pass.json", "production", "pass", []),
    ("run_record_v1_refusal.json", "refusal", "error", ["wrong_serial"]),
    ("run_record_v1_early.json", "production", "pass", []),
])
def test_a_record_of_the_previous_schema_reads_back(name, kind, verdict, causes):
    doc = _doc(name)
    assert doc["schema"] == "eol-cal/run-record/1"
    rec = RunRecord.from_json(doc, name)
    assert (rec.kind, rec.verdict, rec.causes(), record_kind(doc)) == (kind, verdict, causes, kind)
    assert (rec.run_id, rec.serial, rec.started_at, rec.reasons) == (doc["run_id"], doc["serial"], doc["started_at"],
                                                                    tuple(doc["reasons"]))
    migrated = rec.to_json()
    validator("run-record").validate(migrated)
    assert RunRecord.from_json(migrated).to_json() == migrated
    if kind == "production":
        # the checks are the limits judged on the values the record holds: they agree with its verdict
        assert rec.checks and all(c.passed for c in rec.checks)
        assert rec.block("calibrated").crc32 == doc["block"]["crc32"] and rec.block("calibrated").sha256 is None
        assert rec.value("k6") == doc["fit"]["k6"]["value"]
    else:
        assert rec.preflight.problems[0].text == doc["preflight"]["reasons"][0] and rec.blocks == ()


def test_a_version_3_database_written_before_reads_and_migrates(tmp_path):
    """fixtures/records_v3.sqlite: the demo run and the wrong-serial refusal as eol-cal stored them
    before RunRecord (schema version 3, records of schema 1)."""
    db = tmp_path / "records.sqlite"
    shutil.copy(FIXTURES / "records_v3.sqlite", db)
    from eol_cal.records.migrations import SCHEMA_VERSION, migrate
    from eol_cal.records.query import query_records

    assert [(r.serial, r.kind) for r in query_records(db)] == [("DEMO-0001", "production"), ("M-0007", "refusal")]
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(db)])
    assert res.exit_code == 2 and "schema version 3" in res.output and "migrate" in res.output
    assert migrate(db) == (3, SCHEMA_VERSION)
    doc = json.loads(CliRunner().invoke(cli, ["lot", "stats", "--db", str(db), "--json"]).stdout)
    assert (doc["runs"], doc["motors"], doc["first_pass_yield"]) == (1, 1, 1.0)
    assert doc["refusals"] == {"runs": 1, "serials": 1, "pareto": [{"cause": "wrong_serial", "runs": 1, "cumulative": 1.0}]}
    res = CliRunner().invoke(cli, ["records", "--db", str(db), "--json"])
    out = json.loads(res.stdout)
    validator("records").validate(out)
    assert out["summary"]["kinds"]["refusal"] == 1 and out["summary"]["runs"] == 1


@pytest.mark.parametrize(("change", "field"), [
    (lambda d: d.update(kind="retest"), "kind"),
    (lambda d: d["blocks"][1].update(sha256=12), "blocks[1].sha256"),
    (lambda d: d["checks"][0].update(value="big"), "checks[0].value"),
    (lambda d: d["fit"]["k6"].update(value=-1.0), "fit.k6.value"),
    (lambda d: d["captures"]["before"]["ecu_before"].update(crc32="XYZ"), "captures.before.ecu_before.crc32"),
    (lambda d: d.pop("station"), "station"),
    (lambda d: d.update(schema="eol-cal/run-record/9"), "schema"),
])
def test_a_malformed_record_is_refused_naming_the_field(change, field):
    doc = _doc("run_record_demo.json")
    change(doc)
    with pytest.raises(RecordFormatError) as err:
        RunRecord.from_json(doc, "r.json")
    assert err.value.file == "r.json" and err.value.field == field


def test_each_limit_key_is_spelled_once_in_the_library():
    sources = [p for d in ("eol_cal", "cli") for p in (ROOT / d).rglob("*.py")]
    for key in LIMIT_KEYS:
        where = [(p.relative_to(ROOT).as_posix(), n) for p in sources
                 for n in [len(re.findall(rf"\b{key}\b", p.read_text()))] if n]
        assert where == [("eol_cal/records/limits.py", 1)], (key, where)


def test_no_module_outside_the_station_parses_a_record_by_hand():
    """Records are read by RunRecord.from_json (eol_cal/records/parts_json.py, record_v1.py); nothing else
    takes a record document apart."""
    pattern = re.compile(r"""(rec|record)(\.get\(|\[)["'](fit|metrics|limits|block|verdict|captures|ecu_prepared)""")
    offenders = [p.relative_to(ROOT).as_posix() for d in ("eol_cal", "cli") for p in (ROOT / d).rglob("*.py")
                 if pattern.search(p.read_text()) and "station" not in p.parts]
    assert offenders == []


def test_settings_that_cannot_be_flashed_are_a_refusal_with_its_code(tmp_path):
    """The cycle checks the estimator options it will flash before its pre-flight: a library caller's
    bad value ends the run as a refusal (code settings), nothing touched, the record written."""
    from _station_configs import settings_refused_config
    from eol_cal.records.query import query_records
    from eol_cal.station.cycle import run_motor

    cfg = settings_refused_config(tmp_path)
    out = run_motor(cfg)
    rec = out.record
    assert (rec.kind, rec.verdict, rec.refusal_codes, out.exit_code) == ("refusal", "error", ("settings",), 2)
    assert rec.error.step == "pre-flight" and "estimator" in rec.reasons[0] and rec.blocks == ()
    assert [r.run_id for r in query_records(tmp_path / "r.sqlite")] == [rec.run_id]
    validator("run-record").validate(rec.to_json())
