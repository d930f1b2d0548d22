"""``eol-cal index`` and ``eol-cal analyze`` through click's runner and as a subprocess."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.analysis.metrics import eta_percent
from eol_cal.capture import write_capture
from eol_cal.capture.synthetic import synthetic_capture

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_index_table_highlights_the_ppr_and_json_is_stable(tmp_path):
    res = CliRunner().invoke(cli, ["index", "--poles", "6", "--ppr", "64"])
    assert res.exit_code == 0, res.output
    assert "64 <" in res.output and "4.31" in res.output and "0.444" in res.output
    res = CliRunner().invoke(cli, ["index", "--ppr", "100", "--min", "32", "--max", "256", "--json",
                                   "--plot", str(tmp_path / "fig4.png")])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["schema"] == "eol-cal/index/1"
    assert doc["eta_pct"] == pytest.approx(eta_percent(100, 6))
    ppr = [r["ppr"] for r in doc["rows"]]
    assert ppr == sorted(ppr) and ppr[0] == 32 and ppr[-1] == 256 and 100 in ppr and 200 in ppr
    assert [r["ppr"] for r in doc["rows"] if r["selected"]] == [100]
    assert (tmp_path / "fig4.png").read_bytes()[:8] == PNG_MAGIC


@pytest.mark.parametrize("args", [["--poles", "5"], ["--min", "512", "--max", "64"], ["--ppr", "0"],
                                  ["--plot", "/nonexistent-dir/fig.png"]])
def test_index_bad_usage_exits_2(args):
    res = CliRunner().invoke(cli, ["index", *args])
    assert res.exit_code == 2
    assert "Traceback" not in res.output


@pytest.mark.slow  # ~3.5 s on a quiet machine (CONTRIBUTING.md, "Fast or slow")
def test_analyze_fixture_csv_and_mdf4_agree_and_print_pp_and_eta(tmp_path):
    files = [str(FIXTURES / "paper_60rpm.csv"), str(FIXTURES / "paper_60rpm.mf4")]
    res = CliRunner().invoke(cli, ["analyze", *files, "--json", "--plot", str(tmp_path / "a.png")])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["schema"] == "eol-cal/analyze/1" and doc["errors"] == []
    a, b = doc["captures"]
    for c in (a, b):
        assert c["eta_pct"] == pytest.approx(4.306, abs=1e-3)
        assert c["ripple"]["raw_pct"] >= c["ripple"]["filtered_pct"] > 0
        # the fixture's motor has no unbalance: taking mechanical order 1 out changes little
        assert c["ripple"]["no_mech1_pct"] == pytest.approx(c["ripple"]["filtered_pct"], abs=0.1)
        assert c["speed_rpm"] == pytest.approx(60.0, rel=1e-3)
        assert c["quantisation"]["deg_per_count"] == pytest.approx(16.875)
        assert set(c["top_orders"]) == {"6", "12", "18", "mech1"}
        assert len(c["spectrum"]["amplitude_nm"]) == 36
    assert a["ripple"]["raw_pct"] == pytest.approx(b["ripple"]["raw_pct"], rel=1e-3)
    assert a["top_orders"]["6"]["amplitude_nm"] == pytest.approx(b["top_orders"]["6"]["amplitude_nm"], rel=1e-3)
    assert (tmp_path / "a.png").read_bytes()[:8] == PNG_MAGIC
    res = CliRunner().invoke(cli, ["analyze", files[0]])
    assert res.exit_code == 0 and "p-p raw %" in res.output and "eta %" in res.output


def test_analyze_recovers_a_synthetic_6th_harmonic(tmp_path):
    cap = synthetic_capture(rpm=60.0, i_qo=65.0, seconds=2.5, k6=0.00062, phase_k6=0.3, c6=0.004, phase_c6=1.1,
                            theta_r0=0.9)
    write_capture(cap, tmp_path / "s.csv")
    res = CliRunner().invoke(cli, ["analyze", str(tmp_path / "s.csv"), "--json"])
    assert res.exit_code == 0, res.output
    c = json.loads(res.output)["captures"][0]
    # the contract's model -c6 sin(6θ+φc) - k6 i_qo sin(6θ+φk) as one cosine
    z = -0.004 * np.exp(1j * (1.1 - np.pi / 2)) - 0.00062 * 65.0 * np.exp(1j * (0.3 - np.pi / 2))
    assert c["top_orders"]["6"]["amplitude_nm"] == pytest.approx(abs(z), rel=0.01)
    assert abs(np.angle(np.exp(1j * (c["top_orders"]["6"]["phase_rad"] - np.angle(z))))) < np.deg2rad(1.0)
    assert c["ripple"]["window_revs"] == 3 and c["ripple"]["n_windows"] == 2


def test_analyze_reports_the_firmware_angle_on_request():
    res = CliRunner().invoke(cli, ["analyze", str(FIXTURES / "paper_60rpm.mf4"), "--json", "--fw-angle"])
    assert res.exit_code == 0, res.output
    fw = json.loads(res.output)["captures"][0]["firmware_angle"]
    assert fw["rms_deg"] < 0.5 and fw["raw_rms_deg"] > 9.0 and fw["n_ticks"] > 0


def test_analyze_with_a_channel_map_and_refusals(tmp_path):
    res = CliRunner().invoke(cli, ["analyze", str(FIXTURES / "daq_export_foreign.csv"),
                                   "--map", str(FIXTURES / "daq_export_foreign.map.toml"), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["captures"][0]["serial"] == "M-0001"
    # a foreign DAQ's export says nothing of the ECU: analysed, with one warning line
    (warning,) = res.stderr.splitlines()
    assert "daq_export_foreign.csv" in warning and "no record of the ECU state" in warning
    res = CliRunner().invoke(cli, ["analyze", str(FIXTURES / "paper_60rpm.csv"), str(FIXTURES / "bad_hall_fault.csv"),
                                   "--json"])
    assert res.exit_code == 2
    doc = json.loads(res.stdout)
    assert len(doc["captures"]) == 1 and doc["errors"][0]["field"] == "hall"
    res = CliRunner().invoke(cli, ["analyze", str(tmp_path / "missing.csv")])
    assert res.exit_code == 2 and "missing.csv" in res.stderr


@pytest.mark.slow
def test_analyze_and_index_as_subprocess():
    out = subprocess.run([sys.executable, "-m", "cli.main", "analyze", str(FIXTURES / "paper_60rpm.mf4"), "--json"],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["captures"][0]["ripple"]["raw_pct"] > 0
    out = subprocess.run([sys.executable, "-m", "cli.main", "index", "--poles", "7"], capture_output=True, text=True)
    assert out.returncode == 2 and "poles" in out.stderr
