"""``eol-cal fit`` and ``eol-cal table`` on real capture files: recovery, CSV = MDF4, exit codes, block round trip."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.numerics.wrap import wrap_pi
from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture

# two speeds, two loads, and reverse: the delay, c6 and k6 are all identifiable
POINTS = [(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]
# six segments: the same compiled solver shape as most of tests/test_fit_core.py
TRUTH = dict(k6=0.00062, phase_k6=0.3, c6=0.004, phase_c6=1.1)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("fitcli")
    out = {"csv": [], "mf4": []}
    for i, (rpm, iq) in enumerate(POINTS):
        c = synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=i, theta_r0=0.7 * i, serial="M-0007", **TRUTH)
        for ext in ("csv", "mf4"):
            p = d / f"c{i}.{ext}"
            write_capture(c, p)
            out[ext].append(str(p))
    out["dir"] = d
    return out


def _fit(args, runner=None):
    runner = runner or CliRunner()
    return runner.invoke(cli, ["fit", *args], catch_exceptions=False)


@pytest.fixture(scope="module")
def fitted(files):
    out = files["dir"] / "r_csv.json"
    # the analytic generator writes the shaft torque straight from the ripple model: no bench
    res = _fit([*files["csv"], "-o", str(out), "--plot", str(files["dir"] / "plots"), "--bench", "none"])
    return res, out


@pytest.mark.slow
def test_fit_recovers_the_generator_and_writes_the_schema(fitted, files):
    res, out = fitted
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["schema"] == "eol-cal/fit-result/1"
    (m,) = doc["motors"]
    assert m["serial"] == "M-0007" and m["status"] == "ok" and m["reasons"] == []
    assert abs(m["k6"]["value"] - TRUTH["k6"]) < 0.02 * TRUTH["k6"]
    assert abs(wrap_pi(m["phase_k6"]["value"] - TRUTH["phase_k6"])) < math.radians(2)
    assert abs(m["c6"]["value"] - TRUTH["c6"]) < 0.002
    assert abs(wrap_pi(m["phase_c6"]["value"] - TRUTH["phase_c6"])) < math.radians(10)
    for key in ("k6", "phase_k6", "c6", "phase_c6", "delay_s"):
        assert m[key]["ci95"] > 0
    assert -math.pi < m["phase_k6"]["value"] <= math.pi
    assert m["fit"]["converged"] is True and m["fit"]["n_samples"] > 10000 and 0 < m["fit"]["r2"] <= 1
    assert len(m["segments"]) == len(POINTS)
    assert {round(s["speed_rpm"]) for s in m["segments"]} == {120, 240, -120}
    assert m["kt"] == pytest.approx(0.75 * 6 * 0.0109) and m["kt_source"] == "metadata"
    # phases in the firmware estimator's frame; the generator's encoder and halls are exact, so the
    # estimator's frame sits on the hall frame to a small fraction of a degree
    assert m["model"]["angle_frame"] == "firmware" and abs(m["model"]["frame_offset_deg"]) < 0.2
    assert m["model"]["bench"] == "rigid" and all(s["shaft_gain_6"] == 1.0 for s in m["segments"])
    assert m["metrics"]["eta_percent"] > 0 and len(m["metrics"]["captures"]) == len(POINTS)
    assert all("pp_filtered_pct" in c or "error" in c for c in m["metrics"]["captures"])
    assert (files["dir"] / "plots" / "M-0007_fit.png").stat().st_size > 10000
    assert (files["dir"] / "plots" / "M-0007_residual.png").stat().st_size > 5000


def test_same_result_from_csv_and_mdf4(fitted, files):
    _, out_csv = fitted
    out_mf4 = files["dir"] / "r_mf4.json"
    res = _fit([*files["mf4"], "-o", str(out_mf4), "--bench", "none"])
    assert res.exit_code == 0, res.output
    a = json.loads(out_csv.read_text())["motors"][0]
    b = json.loads(out_mf4.read_text())["motors"][0]
    for key in ("k6", "phase_k6", "c6", "phase_c6", "delay_s"):
        assert b[key]["value"] == pytest.approx(a[key]["value"], rel=1e-6, abs=1e-12), key
        assert b[key]["ci95"] == pytest.approx(a[key]["ci95"], rel=1e-4), key
    assert a["fit"]["n_samples"] == b["fit"]["n_samples"]


@pytest.mark.slow
def test_single_load_point_refused_with_exit_2(files, tmp_path):
    # +65 A and -65 A would be two load points (c6 + k6*i_qo takes two values): keep i_qo = +65 A only
    one_load = [f for f, (_, iq) in zip(files["csv"], POINTS, strict=True) if iq == 65.0]
    res = CliRunner().invoke(cli, ["fit", *one_load, "-o", str(tmp_path / "r.json")])
    assert res.exit_code == 2
    assert "not identifiable from a single load point" in res.output
    assert not (tmp_path / "r.json").exists()
    # k6 alone (the paper's eq. 17) is a fair question for one load point, but the generator has
    # cogging (c6 = 10 % of k6 * 65 A) that then leaks into k6 differently at each speed: the
    # between-segment lack of fit (birge about 2.3) widens the interval to about 5 % of k6, so
    # within a 4 % limit it is refused... (the default 5 % sat within 1 % of the widened interval:
    # the fit's mechanical orders since issue 34 took birge from 2.34 to 2.23 and it passed by a
    # hair; the test is about the widening, not that margin) (the generator has no transducer
    # lag: --delay 0)
    out = tmp_path / "r.json"
    args = ["fit", *one_load, "-o", str(out), "--no-c6", "--delay", "0"]
    res = CliRunner().invoke(cli, [*args, "--max-ci-k6", "0.04"])
    assert res.exit_code == 1
    m = json.loads(out.read_text())["motors"][0]
    assert m["status"] == "ci_too_wide" and m["fit"]["birge"] > 2 and m["k6"] is None
    # ... and within wider limits it is a result, about as good as those limits say
    res = CliRunner().invoke(cli, [*args, "--max-ci-k6", "0.3", "--max-ci-phase", "20"])
    assert res.exit_code == 0, res.output
    m = json.loads(out.read_text())["motors"][0]
    assert abs(m["k6"]["value"] - TRUTH["k6"]) < 0.15 * TRUTH["k6"]
    assert m["c6"] == {"value": 0.0, "ci95": 0.0} and m["model"]["fit_c6"] is False
    # the c6 left out moves the k6 phasor identically in both segments: nothing in one load point
    # sees it, so phase_k6 gets no interval (it was 0.378 +- 0.050 rad against 0.30), and says why
    assert abs(wrap_pi(m["phase_k6"]["value"] - TRUTH["phase_k6"])) > 0.05
    assert m["phase_k6"]["ci95"] is None and "one load point" in m["model"]["unchecked"]
    assert "phase intervals of k not given" in res.stderr


@pytest.mark.slow
def test_not_converged_exits_1_without_values_and_no_table(files, tmp_path):
    out = tmp_path / "r.json"
    res = CliRunner().invoke(cli, ["fit", *files["csv"], "-o", str(out), "--max-steps", "1"])
    assert res.exit_code == 1
    m = json.loads(out.read_text())["motors"][0]
    assert m["status"] == "not_converged" and m["k6"] is None and m["phase_k6"] is None and m["reasons"]
    # how the solver ended, by optimistix's name (the file keeps fit.converged only)
    assert "M-0007: the solver ended with nonlinear_max_steps_reached" in res.stderr
    # and no table from it (ci_too_wide is judged the same way: tests/test_fit_core.py)
    res = CliRunner().invoke(cli, ["table", str(out), "-o", str(tmp_path / "b.bin")])
    assert res.exit_code == 1 and "not_converged" in res.output
    assert not (tmp_path / "b.bin").exists()


def test_bad_inputs_exit_2(files, tmp_path):
    res = CliRunner().invoke(cli, ["fit", str(tmp_path / "missing.csv"), "-o", str(tmp_path / "r.json")])
    assert res.exit_code == 2
    bad = tmp_path / "bad.json"
    bad.write_text('{"schema": "something-else"}')
    res = CliRunner().invoke(cli, ["table", str(bad), "-o", str(tmp_path / "b.bin")])
    assert res.exit_code == 2 and "schema" in res.output


def test_table_round_trip(fitted, tmp_path):
    """The block checks valid, and the firmware's i_qc from it matches the fit's analytic i_qc."""
    from eol_cal.firmware.block import check, from_intel_hex, unpack
    from eol_cal.firmware.compensator import block_i_qc, ripple_i_qc

    _, out = fitted
    m = json.loads(out.read_text())["motors"][0]
    blk_path, hex_path = tmp_path / "b.bin", tmp_path / "b.hex"
    res = CliRunner().invoke(cli, ["table", str(out), "-o", str(blk_path), "--hex", str(hex_path), "--table-len", "256"])
    assert res.exit_code == 0, res.output
    data = blk_path.read_bytes()
    assert check(data).valid
    assert from_intel_hex(hex_path.read_text(), 0)[: len(data)] == data
    blk = unpack(data)
    # COMP_ENABLE | INTERP_ENABLE and, by default (best), every estimator option (bits 2-5)
    assert blk.serial == "M-0007" and blk.sequence == 1 and blk.flags == 0x3F and blk.table_len == 256
    assert blk.k6 == pytest.approx(m["k6"]["value"], rel=1e-6)
    assert blk.phase_k6 == pytest.approx(m["phase_k6"]["value"], rel=1e-6)
    assert blk.iqc_limit == pytest.approx(6.5)  # 10 % of the largest |i_qo|
    assert 5e-4 < blk.lead_s < 2e-3  # current loop at 200 Hz plus hold delays
    higher = [(h["order"], h["c"]["value"], h["phase_c"]["value"], h["k"]["value"], h["phase_k"]["value"])
              for h in m["harmonics"]]
    assert [h[0] for h in higher] == [12, 18]
    theta = np.linspace(0, 2 * math.pi, 1000)
    for i_qo in (-65.0, 20.0, 65.0):
        fw = block_i_qc(blk, theta, 0.0, i_qo)  # omega 0: the lead does not move the look-up
        exact = ripple_i_qc(theta, i_qo, m["c6"]["value"], m["phase_c6"]["value"], m["k6"]["value"],
                            m["phase_k6"]["value"], m["kt"], higher)
        assert np.max(np.abs(fw - exact)) < 2e-3 * max(1.0, np.max(np.abs(exact)))
    # a given lead is stored as given
    res = CliRunner().invoke(cli, ["table", str(out), "-o", str(blk_path), "--lead", "0.0001", "--table-len", "64"])
    assert res.exit_code == 0, res.output
    blk = unpack(blk_path.read_bytes())
    assert blk.lead_s == pytest.approx(1e-4) and blk.table_len == 64


@pytest.mark.parametrize("choice, flags", [
    ("best", 0x3F), ("paper", 0x03), ("learn_grid_offset+learn_pitch_errors", 0x2B),
    ("EST_ACCEL_PREDICTION", 0x13), ("0x04", 0x07),
])
def test_table_estimator_options(fitted, tmp_path, choice, flags):
    from eol_cal.firmware.block import flag_names, unpack

    _, out = fitted
    assert json.loads(out.read_text())["motors"][0]["model"]["frame_estimator"] == "best"
    blk_path = tmp_path / "b.bin"
    res = CliRunner().invoke(cli, ["table", str(out), "-o", str(blk_path), "--estimator", choice])
    assert res.exit_code == 0, res.output
    blk = unpack(blk_path.read_bytes())
    assert blk.flags == flags
    text = " ".join(res.output.split())
    # the console folds a long line at its width, inside a word too (where depends on the tmp path's length)
    assert f"flags{flag_names(flags)}" in "".join(text.split())
    # the fit measured its frame under best: another choice is pointed out
    assert ("warning" in text) == (choice != "best")


@pytest.mark.parametrize("choice, why", [("fancy", "unknown estimator option 'fancy'"),
                                         ("0x43", "bits outside the estimator options"),
                                         ("clamp_to_next_edge+", "unknown estimator option ''")])
def test_table_refuses_a_bad_estimator_choice_with_one_line(fitted, tmp_path, choice, why):
    _, out = fitted
    blk_path = tmp_path / "b.bin"
    res = CliRunner().invoke(cli, ["table", str(out), "-o", str(blk_path), "--estimator", choice])
    assert res.exit_code == 2
    assert "--estimator" in res.output and why in res.output
    assert not blk_path.exists()


def test_bench_response_divided_out(fitted, files, tmp_path):
    """With the paper bench the fit reports the motor's ripple: the measured one over the bench's
    shaft response at each segment's 6th (below 1 at 120 rpm, above 1 at 240 rpm: torsion mode)."""
    from eol_cal.domain.bench_mechanics import load_mechanics, shaft_response
    from eol_cal.domain.motor_params import load_motor

    _, out_none = fitted
    out = tmp_path / "r_bench.json"
    res = _fit([*files["csv"], "-o", str(out), "--bench", "paper"])
    assert res.exit_code == 0, res.output
    rigid = json.loads(out_none.read_text())["motors"][0]
    m = json.loads(out.read_text())["motors"][0]
    assert m["model"]["bench"]["name"] == "paper" and m["model"]["bench"]["J_dyno"] == pytest.approx(0.02)
    omega6 = [6 * s["speed_rpm"] * 3 * 2 * math.pi / 60 for s in m["segments"]]
    g = np.abs(shaft_response(np.array(omega6), load_motor("paper"), load_mechanics("paper")))
    assert [s["shaft_gain_6"] for s in m["segments"]] == pytest.approx(list(g), rel=1e-9)
    assert g.min() < 0.997 and g.max() > 1.003
    ratio = m["k6"]["value"] / rigid["k6"]["value"]
    assert 1.0 / g.max() - 1e-3 < ratio < 1.0 / g.min() + 1e-3


def test_bad_bench_exits_2(files, tmp_path):
    res = _fit([*files["csv"], "-o", str(tmp_path / "r.json"), "--bench", "no-such-bench"])
    assert res.exit_code == 2 and "no-such-bench" in res.output
    bad = tmp_path / "bench.toml"
    bad.write_text('J_dyno = 0.02\nK_shaft = -5.0\nshaft_zeta = 0.3\ndyno_bw_hz = 5.0\ndyno_zeta = 0.8\n')
    res = _fit([*files["csv"], "-o", str(tmp_path / "r.json"), "--bench", str(bad)])
    assert res.exit_code == 2 and "K_shaft" in res.output and "bench.toml" in res.output
    assert not (tmp_path / "r.json").exists()


def test_hall_table_measured_by_default_nominal_on_request(fitted, files, tmp_path):
    """The generator's halls are exact: the measured table sits on nominal within the encoder's
    interpolation; ``--hall-angle nominal`` records the contract's table and the block carries it."""
    from eol_cal.firmware.block import unpack
    from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE

    _, out = fitted
    m = json.loads(out.read_text())["motors"][0]
    assert m["hall_angle"]["source"] == "measured" and min(m["hall_angle"]["n_transitions"]) >= 3
    assert max(abs(d) for d in m["hall_angle"]["deviation_deg"]) < 0.5
    out_nom = tmp_path / "nom.json"
    res = _fit([*files["csv"], "-o", str(out_nom), "--bench", "none", "--hall-angle", "nominal"])
    assert res.exit_code == 0, res.output
    nom = json.loads(out_nom.read_text())["motors"][0]
    assert nom["hall_angle"]["source"] == "nominal (asked for)"
    assert nom["hall_angle"]["value"] == pytest.approx(list(NOMINAL_HALL_ANGLE))
    blk = tmp_path / "nom.bin"
    res = CliRunner().invoke(cli, ["table", str(out_nom), "-o", str(blk)], catch_exceptions=False)
    assert res.exit_code == 0 and "hall_angle nominal (asked for)" in res.output
    assert unpack(blk.read_bytes()).hall_angle == pytest.approx(list(NOMINAL_HALL_ANGLE), abs=1e-6)
    # a hand-edited record with a broken table is refused with the field named
    doc = json.loads(out.read_text())
    doc["motors"][0]["hall_angle"]["value"] = [0.1, 0.2]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    res = CliRunner().invoke(cli, ["table", str(bad), "-o", str(tmp_path / "bad.bin")])
    assert res.exit_code == 2 and "hall_angle" in res.output and not (tmp_path / "bad.bin").exists()
