"""``eol-cal capture info|convert`` through click's runner and as a subprocess; fixtures."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from _capture_helpers import assert_same_capture
from click.testing import CliRunner
import pytest

from cli.main import cli
from eol_cal.capture import read_capture

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "fixtures"


def test_info_json_on_mdf4_fixture():
    result = CliRunner().invoke(cli, ["capture", "info", str(FIXTURES / "paper_60rpm.mf4"), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["valid"] is True and doc["problem"] is None
    assert doc["format"] == "mf4" and doc["samples"] == 20000
    assert doc["sample_rate_hz"] == 20000.0 and abs(doc["duration_s"] - 0.99995) < 1e-12
    names = {c["name"]: c for c in doc["channels"]}
    assert names["torque"]["unit"] == "N*m" and 3.0 < names["torque"]["min"] < names["torque"]["max"] < 3.3
    assert names["hall"]["min"] == 1 and names["hall"]["max"] == 6
    assert doc["metadata"]["serial"] == "PAPER-0001" and doc["metadata"]["poles"] == 6
    assert "k6" in doc["truth_keys"] and not any(k.startswith("truth") for k in doc["metadata"])
    # 60 rpm for 1 s: one mechanical revolution, 64 A pulses (the one at t = 0 is the start level)
    assert doc["encoder"]["enc_a_rising_edges"] == 63
    assert doc["encoder"]["edges_per_electrical_rev"] == 64 * 2 / 6
    assert doc["events"] == {"enc_a": 127, "enc_b": 128, "hall": 17}
    assert doc["hall"] == {"states_seen": [1, 2, 3, 4, 5, 6], "changes": 17}


def test_info_human_on_foreign_file_with_map():
    result = CliRunner().invoke(
        cli,
        ["capture", "info", str(FIXTURES / "daq_export_foreign.csv"), "--map", str(FIXTURES / "daq_export_foreign.map.toml")],
    )
    assert result.exit_code == 0, result.output
    for word in ("10000 samples", "torque", "N*m", "M-0001", "valid", "states seen [1, 2, 3, 4, 5, 6]"):
        assert word in result.stdout


def test_info_on_bad_fixture_prints_summary_and_exits_2():
    path = FIXTURES / "bad_hall_fault.csv"
    result = CliRunner().invoke(cli, ["capture", "info", str(path), "--json"])
    assert result.exit_code == 2
    doc = json.loads(result.stdout)
    assert doc["valid"] is False
    assert doc["problem"]["field"] == "hall" and "hall state 7" in doc["problem"]["reason"]
    assert doc["hall"]["states_seen"] == [1, 2, 3, 4, 5, 6, 7]
    assert "bad_hall_fault.csv" in result.stderr and "12 faulty samples" in result.stderr


def test_convert_foreign_to_mdf4_events_and_back(tmp_path):
    out = tmp_path / "m.mf4"
    result = CliRunner().invoke(
        cli,
        ["capture", "convert", str(FIXTURES / "daq_export_foreign.csv"), str(out),
         "--map", str(FIXTURES / "daq_export_foreign.map.toml"), "--digital", "events"],
    )
    assert result.exit_code == 0, result.output
    a = read_capture(FIXTURES / "daq_export_foreign.csv", FIXTURES / "daq_export_foreign.map.toml")
    b = read_capture(out)
    assert_same_capture(a, b, events=False)
    assert set(b.events) == {"enc_a", "enc_b", "hall"}
    csv_out = tmp_path / "back.csv"
    assert CliRunner().invoke(cli, ["capture", "convert", str(out), str(csv_out)]).exit_code == 0
    assert_same_capture(b, read_capture(csv_out), events=False)


def test_convert_refuses_events_for_csv_and_foreign_without_map(tmp_path):
    r = CliRunner().invoke(cli, ["capture", "convert", str(FIXTURES / "paper_60rpm.csv"), str(tmp_path / "x.csv"),
                                 "--digital", "events"])
    assert r.exit_code == 2 and "--digital" in r.stderr
    r = CliRunner().invoke(cli, ["capture", "convert", str(FIXTURES / "daq_export_foreign.csv"), str(tmp_path / "x.mf4")])
    assert r.exit_code == 2 and "'Zeit'" in r.stderr and "--map" in r.stderr
    assert list(tmp_path.iterdir()) == []
    r = CliRunner().invoke(cli, ["capture", "convert", str(FIXTURES / "paper_60rpm.csv"), str(tmp_path / "no" / "x.mf4")])
    assert r.exit_code == 2 and "cannot write" in r.stderr and "x.mf4" in r.stderr


@pytest.mark.slow
def test_subprocess_info_and_bad_exit_code():
    ok = subprocess.run(
        [sys.executable, "-m", "cli.main", "capture", "info", str(FIXTURES / "paper_60rpm.csv"), "--json"],
        capture_output=True, text=True, cwd=ROOT,
    )
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["valid"] is True
    bad = subprocess.run(
        [sys.executable, "-m", "cli.main", "capture", "convert", str(FIXTURES / "bad_hall_fault.csv"), "/nonexistent/x.mf4"],
        capture_output=True, text=True, cwd=ROOT,
    )
    assert bad.returncode == 2
    assert "bad_hall_fault.csv" in bad.stderr and "'hall'" in bad.stderr and "hall state 7" in bad.stderr


@pytest.mark.slow
def test_fixtures_are_small_valid_and_regenerate_identically(tmp_path):
    for name in ("paper_60rpm.csv", "paper_60rpm.mf4", "daq_export_foreign.csv", "bad_hall_fault.csv",
                 "daq_export_daqmx.tdms", "daq_export_tab.txt"):
        assert (FIXTURES / name).stat().st_size < 3_000_000
    out = subprocess.run(
        [sys.executable, str(FIXTURES / "make_fixtures.py"), "--out", str(tmp_path)], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    for name in ("paper_60rpm.csv", "daq_export_foreign.csv", "daq_export_foreign.map.toml", "bad_hall_fault.csv",
                 "daq_export_daqmx.tdms", "daq_export_daqmx.map.toml", "daq_export_tab.txt", "daq_export_tab.map.toml"):
        assert (tmp_path / name).read_bytes() == (FIXTURES / name).read_bytes(), name
    # MDF4 files carry their creation time: compare content
    assert_same_capture(read_capture(tmp_path / "paper_60rpm.mf4"), read_capture(FIXTURES / "paper_60rpm.mf4"))
    csv, mf4 = read_capture(FIXTURES / "paper_60rpm.csv"), read_capture(FIXTURES / "paper_60rpm.mf4")
    assert_same_capture(csv, mf4, events=False)
    assert np.all(np.diff(mf4.events["enc_a"][0]) > 0)
