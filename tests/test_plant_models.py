"""Plant models one by one (numpy): rates, motor, inverter, ripple, dyno, variation, truth."""

import math

import numpy as np
import pytest

from eol_cal.domain.motor_params import load_motor
from eol_cal.domain.bench_mechanics import mech_step
from eol_cal.plant import control, inverter, machine, ripple
from eol_cal.plant.params import PlantSpec, to_params
from eol_cal.plant.presets import paper
from eol_cal.plant.variation import draw_motor


def test_rate_flags_average_exactly_and_jitter_by_one_tick():
    cc = control.rate_flags(20000, 20000.0, 1680.0)
    cmd = control.rate_flags(20000, 20000.0, 420.0)
    assert cc.sum() == 1680 and cmd.sum() == 420
    assert set(np.diff(np.flatnonzero(cc))) == {11, 12}
    assert set(np.diff(np.flatnonzero(cmd))) == {47, 48}
    # a later chunk continues the same schedule
    assert np.array_equal(control.rate_flags(5000, 20000.0, 1680.0, start=7000), cc[7000:12000])


@pytest.mark.parametrize("f_task", [1680.0, 420.0, 1000.0, 333.3, 20000.0])
@pytest.mark.parametrize("start,n", [(0, 0), (0, 1), (3, 249), (7000, 251), (123457, 20001)])
def test_rate_flags_repeat_one_period_of_the_phase_accumulator(f_task, start, n):
    # computed over one period (the ratio's denominator) and repeated: tick k fires where
    # floor(k r) increases, as the accumulator over every tick gives it
    from fractions import Fraction

    r = Fraction(f_task).limit_denominator(10**6) / 20000
    k = np.arange(start, start + n, dtype=np.int64)
    direct = (k * r.numerator) // r.denominator > ((k - 1) * r.numerator) // r.denominator
    got = control.rate_flags(n, 20000.0, f_task, start=start)
    assert got.dtype == direct.dtype and np.array_equal(got, direct)


def test_rl_step_is_exact_for_constant_voltage():
    m = load_motor("paper")
    dt = 1.0 / m.f_pwm
    a, b = machine.rl_coefficients(m.R_s, m.L_q, dt, np)
    i, v = 0.0, 1.5
    for _ in range(200):
        i = a * i + b * v
    t = 200 * dt
    assert i == pytest.approx(v / m.R_s * (1.0 - math.exp(-m.R_s * t / m.L_q)), rel=1e-9)


def test_torque_equation_of_spmsm():
    p = to_params(PlantSpec(), np.zeros(16), np.zeros(16), 0.0, 0.0)
    assert float(machine.electromagnetic_torque(0.0, 65.0, p, 6)) == pytest.approx(load_motor("paper").kt * 65.0, rel=1e-6)


def test_voltage_limit_keeps_angle():
    ua, ub = inverter.limit_voltage(np.array(30.0), np.array(40.0), 12.0, np)
    assert math.hypot(ua, ub) == pytest.approx(12.0 / math.sqrt(3.0), rel=1e-9)
    assert math.atan2(ub, ua) == pytest.approx(math.atan2(40.0, 30.0))
    ua, ub = inverter.limit_voltage(np.array(1.0), np.array(-2.0), 12.0, np)
    assert (ua, ub) == (1.0, -2.0)


def test_ripple_phasor_form_matches_contract_formula():
    spec = paper().replace(c18=0.003, phase_c18=0.7, k12=2e-5, phase_k12=-1.0, unb2=0.003, phase_unb2=2.1,
                           unb3=0.0025, phase_unb3=-0.4)
    p = to_params(spec, np.zeros(16), np.zeros(16), 0.0, 0.0)
    p = p._replace(**{k: np.float64(v) for k, v in ripple.coefficients(spec).items()})
    th_m = np.linspace(0.0, 2.0 * math.pi, 997)
    th_r = 3.0 * th_m
    i_q = 65.0
    got = ripple.ripple_torque(np.cos(th_r), np.sin(th_r), np.cos(th_m), np.sin(th_m), i_q, p)
    want = np.zeros_like(th_r)
    for n in (6, 12, 18):
        want += getattr(spec, f"c{n}") * np.sin(n * th_r + getattr(spec, f"phase_c{n}"))
        want += getattr(spec, f"k{n}") * i_q * np.sin(n * th_r + getattr(spec, f"phase_k{n}"))
    for h in (1, 2, 3):
        want += getattr(spec, f"unb{h}") * np.sin(h * th_m + getattr(spec, f"phase_unb{h}"))
    assert np.max(np.abs(got - want)) < 1e-12


def test_dyno_speed_loop_holds_speed_against_motor_torque():
    spec = PlantSpec()
    p = to_params(spec, np.zeros(16), np.zeros(16), 0.0, 0.0)
    p = p._replace(**{k: np.float64(getattr(p, k)) for k in ("K_shaft", "D_shaft", "Kp_dyno", "Ki_dyno", "J", "B", "J_dyno")})
    dt = 1.0 / spec.motor.f_pwm
    w_ref = 2.0 * math.pi  # 60 rpm
    st = (0.0, 0.0, w_ref, w_ref, 0.0)
    for _ in range(40000):  # 2 s, motor torque stepped to 3 N*m at t = 0
        *st, T_shaft = mech_step(*st, 3.0, w_ref, p, dt, np)
    assert st[3] == pytest.approx(w_ref, rel=1e-3)
    assert T_shaft == pytest.approx(3.0 - spec.motor.B * w_ref, rel=1e-3)


def test_variation_is_deterministic_and_spread():
    a, b, c = draw_motor(7), draw_motor(7), draw_motor(8)
    assert a == b
    assert a != c and a.k6 != c.k6
    assert len(a.enc_edge_err_deg) == 64 and len(a.hall_err_deg) == 6
    k6 = np.array([draw_motor(s).k6 for s in range(200)])
    assert 0.00055 < k6.mean() < 0.00069 and 0.00006 < k6.std() < 0.00013


def test_truth_holds_the_ripple_and_bench():
    truth = draw_motor(3).truth()
    for key in ("k6", "phase_k6", "c6", "phase_c6", "c12", "unb1", "R_s", "temp_degC",
                "enc_edge_err_deg", "hall_err_deg", "transducer_delay_s", "transducer_bw_hz"):
        assert key in truth
    assert not any(k.startswith("truth.") for k in truth)


def test_dead_time_opposes_phase_currents():
    i_a, i_b = 40.0, -10.0
    i_c = -i_a - i_b
    e_al, e_be = inverter.dead_time_error(np.array(i_a), np.array(i_b), np.array(i_c), 0.1, np)
    # the lost voltage vector points against the current vector
    assert e_al * i_a + e_be * (i_b - i_c) / math.sqrt(3.0) < 0.0
    assert math.hypot(e_al, e_be) <= 2.0 / 3.0 * 0.1 * 2.0 + 1e-12


def test_transducer_reading_is_its_output_half_a_tick_on():
    # the tick holds the ripple of its start angle, half a tick behind the continuous chain: the
    # reading beside that angle is the output half a tick on, the mean of the states at the tick's
    # start and end; the end's state led the continuous chain by 25 us (issue 34's k6 bias,
    # tests/test_fit_plant.py)
    from eol_cal.plant import sensors

    p = to_params(paper(), np.zeros(16), np.zeros(16), 0.0, 0.0)
    y, reading = sensors.transducer_step(np.float32(1.0), np.float32(2.0), np.float32(0.0), p, np)
    assert abs(y - (1.0 + float(p.tq_gain))) < 1e-6
    assert abs(reading - (1.0 + 0.5 * float(p.tq_gain))) <= 0.5 * float(p.tq_lsb_nm) + 1e-6
