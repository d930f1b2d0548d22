"""Every command's ``--json`` output names its schema and validates against the schema file shipped
in eol_cal/schemas, on real outputs: fixtures, the plant, a loopback station (pymodbus dyno
simulator, ISO-TP ECU simulator), a records database. Every record kind (pass, fail, error,
refusal, restore) validates as a run record; the schemas are checked without the test extras'
help (the validator is a runtime dependency)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.schemas import SCHEMA_FILES, validator
from eol_cal.sim.loopback import loopback_station
from test_station_run import PROFILE, files, run_args, wait_stopped  # noqa: F401 - the module's fixtures

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
#: the commands that take --json (cli/*.py), each run below
#: (lot baseline needs 2 runs of a station at the least: validated in tests/test_lot_baseline.py; the gate's
#: commands: tests/test_gate_records.py)
JSON_COMMANDS = {"index", "analyze", "fit", "table", "block show", "block check", "capture info", "simulate",
                 "acquire", "flash", "ecu info", "ecu restore", "run", "records", "lot stats", "lot diff",
                 "lot baseline", "msa type1", "gate set", "gate clear", "gate show", "gate history", "gate admitted",
                 "lot simulate"}  # lot simulate's and lot diff --lot's documents: tests/test_lot_simulate.py


def _json(*args: str, code: int | tuple[int, ...] = 0) -> dict:
    res = CliRunner().invoke(cli, list(args))
    assert res.exit_code in ((code,) if isinstance(code, int) else code), res.output
    return json.loads(res.stdout)


def _check(doc: dict) -> str:
    """Validate ``doc`` against the file its schema key names; returns the key."""
    key = doc["schema"]
    validator(SCHEMA_FILES[key]).validate(doc)
    return key


def test_every_json_command_is_covered_here():
    cli_dir = Path(__file__).resolve().parent.parent / "cli"
    options = sum(p.read_text().count('"--json", "as_json"') for p in cli_dir.glob("*.py"))
    assert options == len(JSON_COMMANDS)  # a new --json command: run it below and give it a schema file


@pytest.mark.slow
def test_files_and_plant_commands(tmp_path):
    seen = set()
    seen.add(_check(_json("index", "--json")))
    seen.add(_check(_json("analyze", str(FIXTURES / "paper_60rpm.mf4"), "--json")))
    seen.add(_check(_json("capture", "info", str(FIXTURES / "paper_60rpm.mf4"), "--json")))
    seen.add(_check(_json("block", "show", str(FIXTURES / "block_paper.bin"), "--json")))
    seen.add(_check(_json("block", "check", str(FIXTURES / "block_paper.bin"), "--json")))
    seen.add(_check(_json("table", str(FIXTURES / "fit_paper.json"), "-o", str(tmp_path / "b.bin"), "--json")))
    seen.add(_check(_json("simulate", "-o", str(tmp_path / "s.mf4"), "--speed-rpm", "60", "--iq", "20", "--seconds",
                          "0.3", "--json")))
    lot = _json("simulate", "--motors", "2", "--out-dir", str(tmp_path / "lot"), "--speed-rpm", "60", "--iq", "20",
                "--seconds", "0.3", "--json")
    assert len(lot["motors"]) == 2 and _check(lot) == "eol-cal/simulate/1"
    fit = _json("fit", str(FIXTURES / "paper_60rpm.mf4"), "-o", str(tmp_path / "fit.json"), "--no-c6", "--delay", "0",
                "--json", code=(0, 1))
    seen.add(_check(fit))
    assert seen == {"eol-cal/index/1", "eol-cal/analyze/1", "eol-cal/capture-info/1", "eol-cal/block-show/1",
                    "eol-cal/block-check/1", "eol-cal/table/1", "eol-cal/simulate/1", "eol-cal/fit-result/1"}


@pytest.mark.slow
def test_station_ecu_and_records_commands_and_every_record_kind(files, tmp_path):  # noqa: F811
    """run (pass, refusal), acquire, flash, ecu info, ecu restore (recorded: kind restore), records,
    lot stats and lot diff, on one loopback station and one database."""
    db = tmp_path / "r.sqlite"
    profile = tmp_path / "short.toml"
    profile.write_text(PROFILE)
    seen, kinds = set(), {}
    with loopback_station("J-1", 3, tmp_path / "sim", source=synthetic_source) as st:
        bus = ["-i", "remote", "-c", st.can_channel]
        key = ["--key-file", str(files["key"])]
        doc = _json("acquire", "--dyno", st.dyno_address, "--profile", str(profile), "-o", str(tmp_path / "a.mf4"),
                    *bus, "--json")
        assert doc["ecu"] is not None
        seen.add(_check(doc))
        seen.add(_check(_json("flash", str(FIXTURES / "block_paper.bin"), *bus, *key, "--force", "--json")))
        seen.add(_check(_json("ecu", "info", *bus, "--json")))
        refused = _json(*run_args(files, st, "J-9", db, tmp_path / "reports"), code=2)  # a mis-scan
        seen.add(_check(refused))
        kinds["refusal"] = refused["record"]
        # the analytic source's torque path is a rigid coupling: the bench file that is its own
        run = _json(*run_args(files, st, "J-1", db, tmp_path / "reports", "--bench", "none"), code=(0, 1))
        kinds[run["record"]["verdict"]] = run["record"]
        wait_stopped(st.dyno.sim)
        restore = _json("ecu", "restore", "--run", run["record"]["run_id"], "--db", str(db), *bus, *key, "--force",
                        "--report-dir", str(tmp_path / "reports"), "--json")
    seen.add(_check(restore))
    kinds["restore"] = restore["record"]
    seen.add(_check(_json("records", "--db", str(db), "--json")))
    seen.add(_check(_json("lot", "stats", "--db", str(db), "--json")))
    seen.add(_check(_json("msa", "type1", "--db", str(db), "--serial", "J-1", "--json", code=1)))  # n = 1 < 25
    rows = tmp_path / "refit.jsonl"
    rows.write_text(json.dumps({"serial": "J-1", "verdict": "pass", "status": "ok", "k6": 6e-4, "failed_checks": [],
                                "reasons": [], "error": None}) + "\n")
    seen.add(_check(_json("lot", "diff", "--db", str(db), str(rows), "--json")))
    assert seen == {"eol-cal/acquire/1", "eol-cal/flash/1", "eol-cal/ecu-info/1", "eol-cal/run/1", "eol-cal/ecu-restore/1",
                    "eol-cal/records/2", "eol-cal/lot-stats/2", "eol-cal/lot-diff/1", "eol-cal/msa-type1/1"}
    # every record kind validates as a run record (fail and error from the station's own shapes)
    kinds.setdefault("pass", make_record("P-1").to_json())
    kinds.setdefault("fail", make_record("F-1", k6=2e-3).to_json())
    kinds["error"] = make_record("E-1", error_step="acquire").to_json()
    check = validator("run-record")
    for rec in kinds.values():
        check.validate(rec)
    assert {r["kind"] for r in kinds.values()} == {"production", "refusal", "restore"}
    assert set(kinds) == {"pass", "fail", "error", "refusal", "restore"}


def test_the_validator_says_plainly_what_is_missing(monkeypatch):
    import builtins

    from eol_cal.errors import EolCalError

    real = builtins.__import__

    def no_jsonschema(name, *args, **kwargs):
        if name.split(".")[0] in ("jsonschema", "referencing"):
            raise ImportError(f"No module named {name!r}")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_jsonschema)
    with pytest.raises(EolCalError, match="jsonschema"):
        validator("run-record")


def test_every_schema_file_is_a_valid_schema_and_named_in_the_table():
    import jsonschema

    from eol_cal.schemas import load_schema, schema_names

    for name in schema_names():
        jsonschema.Draft202012Validator.check_schema(load_schema(name))
    assert set(SCHEMA_FILES.values()) <= set(schema_names())
