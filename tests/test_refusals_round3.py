"""The rest of issue 36 (class 9): exit codes, tracebacks, counts and absolute paths.

Bad input is one line naming the option, the file or the key, exit 2, before anything runs:
``lot simulate``'s scheduler, seed and spread; settings and ``--db`` paths no file can have; a
report directory where no run directory can be made; a NaN in an MDF4 header under
``capture info --json``; ``msa type1`` of a serial without runs or with another serial's
reference run; a fit result's ``created`` that is no instant. Restore records keep absolute
paths, as production records do.

Real parts: the CLI through click, SQLite, MDF4 files written by asammdf.
"""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.sim.fuzz import hostile
from eol_cal.sim.fuzz.mutate import base_files
from eol_cal.sim.fuzz.scenarios import station_files
from eol_cal.records.migrations import migrate
from eol_cal.records.write import insert_records

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def _refusal(args: list[str], names: str, **kw) -> str:
    res = CliRunner().invoke(cli, args, **kw)
    assert res.exit_code == 2 and (res.exception is None or isinstance(res.exception, SystemExit)), \
        (res.output, res.exception)
    text = res.stderr.strip()
    assert "Traceback" not in res.output and names in text.splitlines()[-1], res.output
    return text


@pytest.mark.parametrize("extra, names", [
    (["--scheduler", "not a url"], "scheduler"), (["--scheduler", "http://127.0.0.1:1"], "scheduler"),
    (["--seed", "-1"], "--seed"), (["--seed", str(2**70)], "--seed"), (["--seed", str(2**63 - 2)], "--seed"),
    (["--spread", "{d}/empty.toml"], "empty.toml"), (["--spread", "{d}/names-only.toml"], "names-only.toml"),
])
def test_lot_simulate_refuses_before_the_cluster_starts(tmp_path, extra, names):
    (tmp_path / "empty.toml").write_text("")
    (tmp_path / "names-only.toml").write_text('name = "x"\ndescription = "nothing varies"\n')
    _refusal(["lot", "simulate", "--motors", "2", "--limits", str(FIXTURES / "limits.toml"), "--db",
              str(tmp_path / "r.sqlite"), *[e.format(d=tmp_path) for e in extra]], names)
    assert not (tmp_path / "r.sqlite").exists()


@pytest.mark.parametrize("seed", ["-1", str(2**63)])
def test_simulate_refuses_a_seed_numpy_and_jax_cannot_take(tmp_path, seed):
    _refusal(["simulate", "-o", str(tmp_path / "s.csv"), "--seed", seed, "--seconds", "0.1"], "--seed")


def test_a_spread_of_a_negative_mean_with_sigma_rel_draws():
    from eol_cal.plant.spread import parse_spread

    spread = parse_spread({"phase_c6": {"dist": "normal", "mean": -0.3, "sigma_rel": 0.1}}, "s.toml", "s")
    draws = [spread.draw(seed).phase_c6 for seed in range(200)]
    assert abs(sum(draws) / len(draws) + 0.3) < 0.01 and min(draws) < -0.3 < max(draws)


@pytest.mark.parametrize("key, value, names", [
    ("db", '"r\\u0000.sqlite"', "NUL"), ("db", '"' + "x" * 5000 + '.sqlite"', "db"),
    ("db", '"' + "d/" * 2100 + 'r.sqlite"', "db"), ("report_dir", '"' + "y" * 300 + '"', "report_dir"),
    ("spool_dir", '"s\\u0000"', "NUL"), ("report_dir", '"/proc/self"', "report_dir"),
])
def test_run_refuses_paths_no_file_can_have_before_the_dyno(tmp_path, key, value, names):
    for name, data in station_files(**{key: value}).items():
        (tmp_path / name).write_bytes(data)
    _refusal(["run", "--station", str(tmp_path / "station.toml"), "--serial", "M-1"], names)


@pytest.mark.parametrize("command", [["records"], ["lot", "stats"], ["lot", "report", "-o", "x.html"]])
def test_a_db_option_no_file_can_have_is_a_usage_error(command):
    res = CliRunner().invoke(cli, [*command, "--db", "r" * 5000 + ".sqlite"])
    assert res.exit_code == 2 and "longer than a path may be" in res.output and "Traceback" not in res.output


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e999"])
def test_capture_info_json_of_a_non_finite_header_value(tmp_path, value):
    base = base_files()["mdf4"]
    xml = hostile.check_mdf4_bytes(base).header_comment
    path = tmp_path / "c.mf4"
    path.write_bytes(hostile.mdf4_with_header_comment(base, xml.replace("0.049049999999999996", value)))
    res = CliRunner().invoke(cli, ["capture", "info", "--json", str(path)])
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    doc = json.loads(res.stdout)
    assert doc["metadata"]["kt"] is None and doc["valid"] is False and doc["problem"]["field"] == "kt"


def test_msa_type1_of_a_serial_without_runs_and_another_serials_reference(tmp_path):
    db = tmp_path / "r.sqlite"
    migrate(db)
    other = make_record("M-7")
    insert_records(db, [other, *(make_record("MASTER", kind="master", started=f"2026-11-22T1{i}:00:00.000+00:00")
                                 for i in range(3))])
    _refusal(["msa", "type1", "--db", str(db), "--serial", "NOBODY"], "no recorded runs")
    _refusal(["msa", "type1", "--db", str(db), "--serial", "MASTER", "--since", "2027-01-01"], "no recorded runs")
    line = _refusal(["msa", "type1", "--db", str(db), "--serial", "MASTER", "--reference-run", other.run_id],
                    "--reference-run")
    assert "M-7" in line


@pytest.mark.parametrize("created", ["yesterday", "2026-11-24T00:23:36", 20261124, "1969-12-31T23:59:59+00:00",
                                     "2106-02-07T06:28:16+00:00", ""])
def test_table_refuses_a_created_that_is_no_instant(tmp_path, created):
    doc = json.loads((FIXTURES / "fit_paper.json").read_text())
    doc["created"] = created
    (tmp_path / "fit.json").write_text(json.dumps(doc))
    _refusal(["table", str(tmp_path / "fit.json"), "-o", str(tmp_path / "b.bin")], "created")
    assert not (tmp_path / "b.bin").exists()


def test_run_directories_are_absolute_for_every_record_kind(tmp_path, monkeypatch):
    from eol_cal.station.run import new_run_dir

    monkeypatch.chdir(tmp_path)
    d = new_run_dir(Path("reports"), "M-1", dt.datetime(2026, 11, 28, tzinfo=dt.UTC), "ab" * 16)
    assert d.is_absolute() and d.is_dir() and d.parent == tmp_path / "reports"
