"""The estimator's behaviours (paper eqs. 13-16 plus glitch handling) on the golden scenarios.

Each scenario's motion is known, so the outputs are checked against the true angle and speed.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from eol_cal.firmware import contract as C
from eol_cal.firmware import estimator as est
from eol_cal.firmware import estimator_golden as G
from eol_cal.firmware.kinematics import (draw_sensor_errors, electrical_angle, encoder_hall_signals,
                                         speed_profile_angle)

RPM_TO_ELEC = 2.0 * math.pi / 60.0 * 3.0  # rad/s electrical per rpm, 6 poles
DELTA_DEG = 16.875  # one encoder pitch, electrical degrees


@functools.cache
def _run(name: str, cfg: est.EstimatorConfig | None = None):
    sc = G.SCENARIOS[name]
    a, b, h = sc.signals()
    out = est.run(cfg or sc.cfg, a, b, h)
    theta_m = sc.theta_m()
    truth = electrical_angle(theta_m, 6)
    omega = np.gradient(theta_m) * G.TICK_HZ * 3.0
    return a, b, h, out, truth, omega


def _err_deg(x: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.degrees(np.angle(np.exp(1j * (x.astype(np.float64) - truth))))


def _anchored(out: est.EstimatorOut) -> np.ndarray:
    return (out.status & est.ST_NO_ANCHOR) == 0


def _a_rising(a: np.ndarray) -> np.ndarray:
    return np.flatnonzero((a[1:] == 1) & (a[:-1] == 0)) + 1


def test_constant_speed_eqs_13_to_16():
    a, b, h, out, truth, omega = _run("estimator_const_60rpm.csv")
    cfg = G.SCENARIOS["estimator_const_60rpm.csv"].cfg
    edges = _a_rising(a)
    # eq. 15 exactly, in binary32: omega_hat = P*pi / (N_enc * N_c * T) at each edge after the first
    c = est.consts(cfg)
    for k0, k1 in zip(edges[1:-1], edges[2:], strict=True):
        assert out.omega_hat[k1] == c.K_OMEGA / np.float32(k1 - k0)
    # eq. 16: between edges theta_hat advances by omega_hat*T per tick
    k0, k1 = edges[5], edges[6]
    steps = np.diff(out.theta_hat[k0:k1].astype(np.float64))
    assert np.allclose(steps, float(out.omega_hat[k0]) / G.TICK_HZ, rtol=1e-3)
    # the speed is right within the edge placement error, the angle within a degree or so
    ok = np.arange(len(a)) > edges[2]
    assert np.max(np.abs(out.omega_hat[ok] / omega[ok] - 1.0)) < 0.05
    e = _err_deg(out.theta_hat, truth)[ok]
    assert np.sqrt(np.mean(e**2)) < 1.2 and np.max(np.abs(e)) < 4.0
    # the raw angle is the staircase of one pitch: the last edge's angle, behind the rotor by
    # [0, DELTA) plus the sensor errors, standard deviation DELTA/sqrt(12) = 4.87 deg
    er = _err_deg(out.theta_enc, truth)[ok]
    assert er.min() > -DELTA_DEG - 3.0 and er.max() < 3.0 and 4.0 < np.std(er) < 6.0
    assert out.status[ok].max() == 0


def test_startup_uses_the_hall_sector_until_the_first_transition():
    a, b, h, out, truth, _ = _run("estimator_const_60rpm.csv")
    cfg = G.SCENARIOS["estimator_const_60rpm.csv"].cfg
    first_transition = int(np.argmax(h != h[0]))
    c = est.consts(cfg)
    before = slice(0, first_transition)
    assert np.all(out.status[before] & est.ST_NO_ANCHOR)
    assert np.all(out.theta_hat[before] == c.H_MID[h[0]])
    assert np.all(out.omega_hat[:int(_a_rising(a)[1])] == 0.0)
    assert not out.status[first_transition] & est.ST_NO_ANCHOR
    # at the transition the absolute angle comes from the table: where state h begins forward
    assert abs(_err_deg(out.theta_hat, truth)[first_transition]) < 3.0


def test_ramp_30_to_85_rpm_tracks_speed_and_angle():
    a, b, h, out, truth, omega = _run("estimator_ramp_30_85rpm.csv")
    ok = np.arange(len(a)) > _a_rising(a)[3]
    e = _err_deg(out.theta_hat, truth)[ok]
    assert np.sqrt(np.mean(e**2)) < 1.5
    # omega_hat is the last interval's mean speed: it lags this steep ramp (30 -> 85 rpm in 0.4 s)
    # by up to one interval's speed change
    assert np.max(np.abs(out.omega_hat[ok] / omega[ok] - 1.0)) < 0.15
    edges = _a_rising(a)[4:]
    mid_interval = omega[edges] - np.diff(omega)[edges] * np.diff(_a_rising(a))[3:] / 2
    assert np.max(np.abs(out.omega_hat[edges] / mid_interval - 1.0)) < 0.08
    assert out.omega_hat[-1] > 80 * RPM_TO_ELEC


@pytest.mark.slow
def test_creep_1_rpm_is_measured_not_standstill():
    a, b, h, out, truth, omega = _run("estimator_creep_1rpm.csv")
    edges = _a_rising(a)
    assert len(edges) == 2 and edges[1] - edges[0] > 18000  # N_c near 18750 ticks
    assert not np.any(out.status & est.ST_STANDSTILL)
    assert out.omega_hat[-1] == pytest.approx(1.0 * RPM_TO_ELEC, rel=0.03)
    # before the second edge there is no measured speed: the angle is the quadrature count's middle
    mid = slice(int(np.argmax(_anchored(out))), int(edges[1]))
    assert np.all(out.status[mid] & est.ST_NO_SPEED)
    assert np.max(np.abs(_err_deg(out.theta_hat, truth)[mid])) < DELTA_DEG / 4 / 2 + 3.0


@pytest.mark.parametrize("name", ["estimator_standstill_restart.csv", "estimator_standstill_restart_all.csv"])
def test_standstill_and_restart(name):
    a, b, h, out, truth, omega = _run(name)
    cfg = G.SCENARIOS[name].cfg
    still = (out.status & est.ST_STANDSTILL) != 0
    edges = _a_rising(a)
    assert still.any()
    i0 = int(np.argmax(still))
    last_edge = int(edges[edges < i0][-1])
    assert i0 - last_edge == cfg.standstill_ticks + 1  # declared after standstill_ticks without an edge
    assert np.all(out.omega_hat[still] == 0.0)
    # at standstill the angle stays inside the hall sector and near the truth (count middle)
    e_still = _err_deg(out.theta_hat, truth)[still]
    assert np.max(np.abs(e_still)) < 5.0
    # restart: standstill clears at the first edge, the speed comes back at the second
    restart = int(edges[edges > i0][0])
    assert not still[restart] and np.all(~still[restart:])
    second = int(edges[edges > restart][0])
    assert out.omega_hat[second - 1] == 0.0 and out.omega_hat[second] > 0.0
    assert abs(out.omega_hat[-1] / (60 * RPM_TO_ELEC) - 1.0) < 0.05


def test_stop_overshoot_paper_vs_clamp():
    """The paper's prediction runs on at the last speed until standstill; improvement 1 does not."""
    _, _, _, paper, truth, _ = _run("estimator_standstill_restart.csv")
    _, _, _, best, _, _ = _run("estimator_standstill_restart_all.csv")
    stop = slice(2000, 5000)  # decelerating and at rest
    e_paper = np.max(np.abs(_err_deg(paper.theta_hat, truth)[stop]))
    e_best = np.max(np.abs(_err_deg(best.theta_hat, truth)[stop]))
    assert e_paper > 20.0 and e_best < 5.0


def test_reverse_rotation_constant_speed():
    a, b, h, out, truth, omega = _run("estimator_reverse_60rpm.csv")
    ok = np.arange(len(a)) > _a_rising(a)[2]
    assert np.all(out.status[ok] & est.ST_REVERSE)
    assert np.all(out.omega_hat[ok] < 0)
    assert out.omega_hat[-1] == pytest.approx(-60 * RPM_TO_ELEC, rel=0.03)
    e = _err_deg(out.theta_hat, truth)[ok & _anchored(out)]
    assert np.sqrt(np.mean(e**2)) < 1.2
    # in reverse the raw angle is the last edge's, ahead of the rotor: error in [0, DELTA)
    er = _err_deg(out.theta_enc, truth)[ok & _anchored(out)]
    assert er.min() > -3.0 and er.max() < DELTA_DEG + 3.0


def test_reversal_paper_and_best():
    a, b, h, out, truth, omega = _run("estimator_reversal.csv")
    assert not out.status[2500] & est.ST_REVERSE and out.status[-1] & est.ST_REVERSE
    assert out.omega_hat[2500] > 0 and out.omega_hat[-1] == pytest.approx(-60 * RPM_TO_ELEC, rel=0.05)
    # the reversal edge gives no speed (its interval is not a pitch)
    flips = np.flatnonzero(np.diff((out.status & est.ST_REVERSE) != 0)) + 1
    assert len(flips) == 1 and out.omega_hat[flips[0]] == 0.0
    late = slice(5000, None)
    assert np.sqrt(np.mean(_err_deg(out.theta_hat, truth)[late] ** 2)) < 1.5
    best = est.run(est.EstimatorConfig.best(), a, b, h)
    assert np.max(np.abs(_err_deg(best.theta_hat, truth)[400:])) < 6.0


def test_missing_edge_is_detected_and_the_count_restored():
    name = "estimator_missing_edge.csv"
    a, b, h, out, truth, omega = _run(name)
    miss = np.flatnonzero(out.status & est.ST_MISSING_EDGE)
    assert len(miss) == 1
    i = int(miss[0])
    # speed from half the doubled interval, not half the speed
    assert out.omega_hat[i] == pytest.approx(60 * RPM_TO_ELEC, rel=0.05)
    e = _err_deg(out.theta_hat, truth)
    assert np.max(np.abs(e[i:])) < 3.0
    # without the correction the count would stay a pitch behind until the next hall transition
    ca, cb, ch = G.SCENARIOS[name].clean_signals()
    clean = est.run(G.SCENARIOS[name].cfg, ca, cb, ch)
    hall_after = i + int(np.argmax(h[i:] != h[i]))
    assert np.array_equal(out.theta_enc[i:hall_after], clean.theta_enc[i:hall_after])


def test_edge_bounce_gives_no_absurd_speed_or_jump():
    name = "estimator_edge_bounce.csv"
    a, b, h, out, truth, omega = _run(name)
    assert np.max(np.abs(out.omega_hat)) < 1.1 * 60 * RPM_TO_ELEC
    jumps = np.degrees(np.abs(np.angle(np.exp(1j * np.diff(out.theta_hat.astype(np.float64))))))
    anchored = _anchored(out)[:-1]  # a jump from the sector middle onto the first anchor is fine
    assert np.max(jumps[anchored]) < 5.0
    assert np.count_nonzero(out.status & est.ST_EDGE_REJECT) >= 3
    # the bounces change nothing after they settle: same angle as the clean signals
    ca, cb, ch = G.SCENARIOS[name].clean_signals()
    clean = est.run(G.SCENARIOS[name].cfg, ca, cb, ch)
    assert np.max(np.abs(_err_deg(out.theta_hat, clean.theta_hat.astype(np.float64))[2600:])) < 0.5


def test_hall_glitches_are_ignored():
    name = "estimator_hall_glitch.csv"
    a, b, h, out, truth, _ = _run(name)
    ca, cb, ch = G.SCENARIOS[name].clean_signals()
    clean = est.run(G.SCENARIOS[name].cfg, ca, cb, ch)
    assert np.array_equal(out.theta_hat, clean.theta_hat)
    assert np.array_equal(out.omega_hat, clean.omega_hat)
    fault = np.flatnonzero(out.status & est.ST_HALL_FAULT)
    seq = np.flatnonzero(out.status & est.ST_HALL_SEQ)
    assert fault.tolist() == [700, 701, 1500]
    assert seq.tolist() == [2200, 2201]  # into the opposite sector and back: both ignored


def test_invalid_hall_at_power_on_waits_for_a_valid_state():
    sc = G.SCENARIOS["estimator_const_60rpm.csv"]
    a, b, h = sc.signals()
    h = h.copy()
    h[:50] = 7
    out = est.run(sc.cfg, a, b, h)
    assert np.all(out.status[:50] & est.ST_HALL_FAULT) and np.all(out.theta_hat[:50] == 0.0)
    c = est.consts(sc.cfg)
    assert out.theta_hat[50] == c.H_MID[h[50]]


def test_direction_mismatch_and_quadrature_error_are_flagged():
    theta_m = speed_profile_angle(((0.2, 60.0, 60.0),), G.TICK_HZ, 0.3)
    a, b, h = encoder_hall_signals(theta_m, 6, 64, draw_sensor_errors(np.random.default_rng(1), 64))
    swapped = est.run(est.EstimatorConfig.paper(), b, a, h)  # encoder wired backwards
    assert np.count_nonzero(swapped.status & est.ST_DIR_MISMATCH) >= 3
    # a sample where A and B both change: the step is ambiguous and not counted
    idx = np.flatnonzero(np.diff(a) != 0)[10] + 1
    a2, b2 = a.copy(), b.copy()
    j = idx + int(np.argmax(b[idx:] != b[idx]))  # next B change
    a2[idx:j] = a2[idx - 1]
    b2[idx:j] = b[idx - 1]
    a2[j], b2[j] = a[j], b[j]
    out = est.run(est.EstimatorConfig.paper(), a2, b2, h)
    assert out.status[j] & est.ST_QEP_ERROR


def test_config_validation_and_flags():
    with pytest.raises(ValueError):
        est.EstimatorConfig.paper(hall_angle=(0.0,) * 5)
    with pytest.raises(ValueError):
        est.EstimatorConfig(poles=5, N_enc=64, tick_hz=2e4, hall_angle=est.NOMINAL_HALL_ANGLE, standstill_ticks=10)
    with pytest.raises(ValueError):
        est.EstimatorConfig.paper(standstill_s=1e5)
    # the configuration as the block flags word that selects it (contract bits 1 and 2-5)
    assert est.EstimatorConfig.paper().flags == C.FLAG_INTERP_ENABLE and est.EstimatorConfig.paper().options == 0
    assert est.EstimatorConfig.best().flags == C.FLAG_INTERP_ENABLE | C.FLAGS_ESTIMATOR == 0x3E
    assert est.EstimatorConfig.all_improvements() == est.EstimatorConfig.best()
    assert est.EstimatorConfig.paper(learn_grid_offset=True).options == C.FLAG_EST_LEARN_GRID_OFFSET == 0x08


def test_from_block_takes_the_block_fields():
    class Blk:
        poles, encoder_ppr, tick_hz = 8, 128, 16000.0
        hall_angle = tuple(math.radians(d) for d in (61, 181, 121, 301, 1, 241))
        flags = C.FLAG_INTERP_ENABLE | C.FLAG_EST_LEARN_PITCH_ERRORS

    cfg = est.EstimatorConfig.from_block(Blk(), clamp_to_next_edge=True)
    assert (cfg.poles, cfg.N_enc, cfg.tick_hz, cfg.standstill_ticks) == (8, 128, 16000.0, 16000)
    assert cfg.hall_angle[0] == float(np.float32(math.radians(61))) and cfg.clamp_to_next_edge
    # the options come from the block's flags, named ones on top
    assert cfg.learn_pitch_errors and not cfg.learn_grid_offset and not cfg.accel_prediction


@pytest.mark.parametrize("flags, options", [
    (0, 0),
    (C.FLAG_INTERP_ENABLE, 0),
    (C.FLAG_INTERP_ENABLE | C.FLAGS_ESTIMATOR, C.FLAGS_ESTIMATOR),
    (C.FLAG_COMP_ENABLE | C.FLAGS_ESTIMATOR, 0),  # options without INTERP_ENABLE: not honoured
    (C.FLAG_INTERP_ENABLE | C.FLAG_EST_ACCEL_PREDICTION, C.FLAG_EST_ACCEL_PREDICTION),
])
def test_block_flags_select_the_options(flags, options):
    cfg = est.EstimatorConfig.from_flags(flags)
    assert cfg.options == options
    assert sum(bit for name, bit in est.OPTION_FLAGS.items() if est.options_from_flags(flags)[name]) == options


def test_wrap_edges():
    x = np.array([-1e-8, 0.0, 2 * math.pi, -2 * math.pi, 7.0, -7.0, 100.0], np.float32)
    w = est.wrap(x)
    assert np.all(w >= 0) and np.all(w < est.TWO_PI) and w.dtype == np.float32
    assert np.all(np.abs(est.wrap_pm(np.float32(math.pi))) <= est.PI)
