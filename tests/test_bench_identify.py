"""The bench identified at commissioning (issue 34): the sweep's phasors, the identification, its
refusals, the bench file it writes (read back by the fit's loader), the spread's station bench,
and ``eol-cal bench identify`` on the plant's sweep."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.analysis.bench_id.identify import identify_bench, path_response
from eol_cal.analysis.bench_id.output import bench_toml, write_bench
from eol_cal.analysis.bench_id.sweep import SweepPoints, segment_phasors
from eol_cal.errors import InputError
from eol_cal.domain.bench_mechanics import BenchMechanics, load_mechanics, torsion_response
from eol_cal.domain.motor_params import load_motor

MOTOR = load_motor("paper")
KT = MOTOR.kt


def _bench(f_n: float, zeta: float, bw: float | None = 60.0, delay: float = 20e-6) -> BenchMechanics:
    J, J_d = MOTOR.J, 0.02
    return BenchMechanics(name="truth", J_dyno=J_d, K_shaft=(2 * math.pi * f_n) ** 2 * J * J_d / (J + J_d),
                          shaft_zeta=zeta, dyno_bw_hz=5.0, dyno_zeta=0.8, transducer_bw_hz=bw, transducer_delay_s=delay)


def _points(bench: BenchMechanics, rpms, rel_noise: float = 0.003, seed: int = 0, distort=None,
            loads=(40.0,)) -> SweepPoints:
    """Points of a sweep through ``bench``: the motor's ripple Z_h (``c_h + k_h i_qo``) plus kt
    times a current ripple that grows with speed, through the path, with noise of known standard
    error; the segments take ``loads`` (A) in turn."""
    rng = np.random.default_rng(seed)
    c = {6: 0.004 * np.exp(0.6j), 12: 0.009 * np.exp(-2.1j), 18: 0.003 * np.exp(1.2j)}
    k = {6: 0.00062 * np.exp(1.6j), 12: 0.0, 18: 0.0}
    rows = []
    for s, rpm in enumerate(rpms):
        i_qo = loads[s % len(loads)]
        Z = {h: c[h] + k[h] * i_qo for h in c}
        for h in (6, 12, 18):
            w = h * rpm * 3 * 2 * math.pi / 60
            i_q = 1e-4 * rpm * np.exp(1j * (0.3 * h + rpm / 500))  # A: the ECU's current ripple
            M = path_response(np.array([w]), MOTOR, bench)[0] * (Z[h] + KT * i_q)
            if distort is not None:
                M *= distort(w)
            se_M = rel_noise * 0.03 + 2e-5
            M += se_M * (rng.normal() + 1j * rng.normal())
            se_Iq = 0.002
            rows.append((w, h, s, rpm, i_qo, M, se_M, i_q + se_Iq * (rng.normal() + 1j * rng.normal()), se_Iq))
    cols = list(zip(*rows, strict=True))
    return SweepPoints("MASTER-T", ["sweep.mf4"], KT, *(np.asarray(c) for c in cols))


SWEEP = [60] + list(range(100, 1501, 50))


def test_segment_phasors_recover_known_harmonics():
    theta = np.linspace(0, 2 * math.pi * 7, 20000)
    y = 0.01 + 0.03 * np.cos(6 * theta + 0.4) + 0.005 * np.sin(12 * theta) + 0.002 * np.cos(theta / 3 + 1.0)
    rng = np.random.default_rng(1)
    y_noisy = y + 0.002 * rng.normal(size=theta.size)
    ph, se = segment_phasors(theta, 3, np.stack([y_noisy, 2 * y], axis=1))
    # T = Re(M exp(i h theta)): 0.03 cos(6 theta + 0.4) -> 0.03 exp(0.4 i); 0.005 sin(12 theta) -> -0.005 i
    assert abs(ph[0, 0] - 0.03 * np.exp(0.4j)) < 4 * se[0, 0]
    assert abs(ph[1, 0] - (-0.005j)) < 4 * se[1, 0]
    assert ph[0, 1] == pytest.approx(0.06 * np.exp(0.4j), abs=1e-9)
    assert 1e-5 < se[0, 0] < 1e-4


def test_identifies_the_torsion_mode_and_transducer_with_intervals():
    truth = _bench(250.0, 0.1)
    res = identify_bench(_points(truth, SWEEP), MOTOR, load_mechanics("paper"), name="ident")
    e = res.estimates
    assert abs(e["f_n_hz"].value - 250.0) <= e["f_n_hz"].ci95 and e["f_n_hz"].ci95 < 5.0
    assert abs(e["shaft_zeta"].value - 0.1) <= e["shaft_zeta"].ci95
    assert abs(e["K_shaft"].value - truth.K_shaft) <= e["K_shaft"].ci95
    assert abs(e["transducer_bw_hz"].value - 60.0) <= e["transducer_bw_hz"].ci95
    assert abs(e["transducer_delay_s"].value - 20e-6) <= e["transducer_delay_s"].ci95
    # the dyno's speed loop is invisible at these frequencies: held, and said so
    assert e["dyno_bw_hz"].status == "held" and e["dyno_bw_hz"].value == 5.0 and "at most" in e["dyno_bw_hz"].note
    assert res.mechanics.name == "ident" and res.birge < 1.5 and not res.dropped
    # the shaft line (what the fit divides out) at the calibration's frequencies (18 .. 108 Hz)
    w = 2 * math.pi * np.array([18.0, 36.0, 108.0])
    g_id, g_true = (torsion_response(w, MOTOR.J, MOTOR.B, b) for b in (res.mechanics, truth))
    assert np.abs(g_id / g_true - 1).max() < 0.002


def test_sweep_at_two_loads_fits_the_ripple_as_c_plus_k_i():
    truth = _bench(300.0, 0.2)
    pts = _points(truth, SWEEP, loads=(20.0, 65.0), seed=3)
    res = identify_bench(pts, MOTOR, load_mechanics("paper"))
    e = res.estimates
    assert abs(e["f_n_hz"].value - 300.0) <= e["f_n_hz"].ci95 and abs(e["shaft_zeta"].value - 0.2) <= e["shaft_zeta"].ci95
    # two loads: each harmonic's ripple is c + k i_qo, and k6 comes out as the motor's
    assert all(v.shape == (2,) for v in res.ripple.values())
    assert abs(res.ripple[6][1] - 0.00062 * np.exp(1.6j)) < 0.02 * 0.00062


def test_too_few_speeds_refused():
    with pytest.raises(InputError) as exc:
        identify_bench(_points(_bench(250.0, 0.1), [100, 400, 800, 1200]), MOTOR, load_mechanics("paper"))
    assert exc.value.field == "speed_rpm" and "too few speeds" in exc.value.reason and exc.value.file == "sweep.mf4"


def test_resonance_above_the_sweep_refused():
    # a stiff bench (1500 Hz) swept to 400 rpm: the 18th reaches 360 Hz, nowhere near the mode
    with pytest.raises(InputError) as exc:
        identify_bench(_points(_bench(1500.0, 0.1, bw=None, delay=0.0), range(60, 401, 20)), MOTOR,
                       load_mechanics("paper"))
    assert exc.value.field in ("speed_rpm", "K_shaft"), exc.value
    assert "outside the sweep" in exc.value.reason or "does not determine" in exc.value.reason


def test_inconsistent_model_refused():
    # a second mode the two-inertia model does not have (a transducer resonance at 600 Hz)
    def second_mode(w):
        wn = 2 * math.pi * 600
        return wn ** 2 / (wn ** 2 - w ** 2 + 2j * 0.05 * wn * w)

    with pytest.raises(InputError) as exc:
        identify_bench(_points(_bench(250.0, 0.1), SWEEP, distort=second_mode), MOTOR, load_mechanics("paper"))
    assert exc.value.field == "model" and "Birge ratio" in exc.value.reason


def test_bench_file_round_trip(tmp_path):
    res = identify_bench(_points(_bench(250.0, 0.1), SWEEP), MOTOR, load_mechanics("paper"), name="station-7")
    path = tmp_path / "station-7.toml"
    write_bench(res, path)
    back = load_mechanics(path)
    assert back == res.mechanics  # source and sha256 are not compared
    assert back.source == str(path) and len(back.sha256) == 64
    assert back.transducer_bw_hz == pytest.approx(res.estimates["transducer_bw_hz"].value)
    import tomllib

    ident = tomllib.loads(path.read_text())["identification"]
    assert ident["K_shaft"]["ci95"] > 0 and ident["dyno_bw_hz"]["status"] == "held"
    assert ident["master_serial"] == "MASTER-T" and ident["points"] == len(SWEEP) * 3
    assert bench_toml(res) == path.read_text()


@pytest.mark.parametrize("line, field", [
    ("transducer_delay_s = 2.0\n", "transducer_delay_s"),
    ("transducer_bw_hz = 0.0\n", "transducer_bw_hz"),
    ("identification = 3\n", "identification"),
])
def test_bench_file_transducer_keys_checked(tmp_path, line, field):
    p = tmp_path / "b.toml"
    p.write_text("J_dyno = 0.02\nK_shaft = 270.0\nshaft_zeta = 0.1\ndyno_bw_hz = 5.0\ndyno_zeta = 0.8\n" + line)
    with pytest.raises(InputError) as exc:
        load_mechanics(p)
    assert exc.value.field == field and "b.toml" in str(exc.value)


def test_paper_bench_unchanged_by_the_new_keys():
    paper = load_mechanics("paper")
    assert paper.transducer_bw_hz is None and paper.transducer_delay_s is None and paper.source == "bench paper"
    assert dataclasses.replace(paper, source="elsewhere") == paper


def test_spread_draws_one_bench_per_station(tmp_path):
    from eol_cal.plant.spread import load_spread
    from eol_cal.plant.variation import draw_motor

    spread = load_spread("default")
    a, b = spread.draw_bench(3), spread.draw_bench(3)
    assert a.mechanics == b.mechanics and a.mechanics != spread.draw_bench(4).mechanics
    J, J_d = a.motor.J, a.mechanics.J_dyno
    f_n = math.sqrt(a.mechanics.K_shaft * (J + J_d) / (J * J_d)) / (2 * math.pi)
    assert 150.0 <= f_n <= 400.0 and 0.05 <= a.mechanics.shaft_zeta <= 0.3
    # the lot's motors on that bench are the same motors as without it (the bench has its own stream)
    m = spread.draw(11, base=a)
    assert m.mechanics == a.mechanics and m.k6 == draw_motor(11).k6 and m.unb1 == draw_motor(11).unb1
    bad = tmp_path / "s.toml"
    bad.write_text("[bench.resonance_hz]\ndist = 'uniform'\nlow = 1.0\nhigh = 400.0\n")
    with pytest.raises(InputError) as exc:
        load_spread(bad)
    assert exc.value.field == "bench.resonance_hz" and "range" in exc.value.reason
    bad.write_text("[bench.stiffness]\ndist = 'fixed'\nvalue = 1.0\n")
    with pytest.raises(InputError) as exc:
        load_spread(bad)
    assert exc.value.field == "bench.stiffness"


def test_cli_refuses_a_sweep_without_current_or_speeds(tmp_path):
    from eol_cal.capture.io import write_capture
    from eol_cal.capture.synthetic import synthetic_capture

    paths = []
    for i, rpm in enumerate((200.0, 400.0, 600.0)):
        c = synthetic_capture(rpm=rpm, i_qo=40.0, seconds=0.4, seed=i, serial="MASTER-S")
        paths.append(tmp_path / f"s{i}.csv")
        write_capture(c, paths[-1])
    out = tmp_path / "bench.toml"
    res = CliRunner().invoke(cli, ["bench", "identify", *map(str, paths), "-o", str(out)])
    assert res.exit_code == 2 and "iq" in res.output and "missing channel" in res.output
    for i, rpm in enumerate((200.0, 400.0, 600.0)):
        c = synthetic_capture(rpm=rpm, i_qo=40.0, seconds=0.4, seed=i, serial="MASTER-S")
        c.channels["iq"] = np.full_like(c.t, 40.0)
        write_capture(c, paths[i])
    res = CliRunner().invoke(cli, ["bench", "identify", *map(str, paths), "-o", str(out)])
    assert res.exit_code == 2 and "too few speeds" in res.output and "speed_rpm" in res.output
    assert not out.exists()


@pytest.mark.slow
def test_identify_the_plants_resonant_bench_and_fit_with_it(tmp_path):
    """The master motor's sweep on the plant's resonant-250 bench: ``eol-cal bench identify``
    finds the mode the plant integrates (its semi-implicit Euler moves it +0.4 % from the nominal
    250 Hz) within its interval, the transducer's 60 Hz, and the file it writes is what a fit with
    ``--bench FILE`` records it assumed."""
    import json
    import tomllib

    from eol_cal.capture.io import write_capture
    from eol_cal.capture.synthetic import synthetic_capture
    from eol_cal.plant.presets import paper
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.variation import draw_motor

    base = paper().replace(mechanics=load_mechanics("resonant-250"))
    master = draw_motor(1001, base=base, serial="MASTER-1001")
    sweep = load_profile("bench-sweep")
    (run,) = simulate([master], sweep, mode="estimated", seed=0)
    starts = np.cumsum([0.0] + [s.seconds for s in sweep.segments[:-1]])
    run.capture.metadata["segment_starts"] = ",".join(f"{s:.6f}" for s in starts)
    cap = tmp_path / "sweep.mf4"
    write_capture(run.capture, cap)
    out, png = tmp_path / "ident.toml", tmp_path / "ident.png"
    res = CliRunner().invoke(cli, ["bench", "identify", str(cap), "-o", str(out), "--plot", str(png)])
    assert res.exit_code == 0, res.output
    ident = tomllib.loads(out.read_text())["identification"]
    f_plant = 251.06  # Hz: the plant's discrete shaft line (bench/bench_bench_identify.py discrete_mode)
    assert abs(ident["f_n_hz"]["value"] - f_plant) <= ident["f_n_hz"]["ci95"] < 3.0
    assert abs(ident["shaft_zeta"]["value"] - 0.101) <= ident["shaft_zeta"]["ci95"]
    assert abs(ident["transducer_bw_hz"]["value"] - 60.0) <= ident["transducer_bw_hz"]["ci95"]
    assert png.stat().st_size > 10_000
    assert ident["speeds"] == len(sweep.segments) and "left out" not in res.output  # every speed used
    # a fit with the identified file records which bench it assumed
    files = []
    for i, (rpm, iq) in enumerate([(120.0, 20.0), (120.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]):
        files.append(tmp_path / f"c{i}.csv")
        write_capture(synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=i, serial="M-1"), files[-1])
    result = tmp_path / "fit.json"
    res = CliRunner().invoke(cli, ["fit", *map(str, files), "-o", str(result), "--bench", str(out)])
    assert res.exit_code in (0, 1), res.output
    bench = json.loads(result.read_text())["motors"][0]["model"]["bench"]
    assert bench["source"] == str(out) and bench["name"] == "ident" and len(bench["sha256"]) == 64
