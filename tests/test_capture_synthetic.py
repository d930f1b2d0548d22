"""The analytic capture model: contract conventions, exact events, the paper's quantisation ripple."""

from __future__ import annotations

import numpy as np
import pytest

from eol_cal.capture import validate
from eol_cal.capture.columns import zoh
from eol_cal.capture.synthetic import hall_state, synthetic_capture
from eol_cal.domain.motor_params import load_motor

KT = load_motor("paper").kt


def _sequence(hall):
    return hall[np.r_[True, np.diff(hall) != 0]].tolist()


def test_hall_convention_of_the_contract():
    deg = np.array([30, 90, 150, 210, 270, 330])
    assert hall_state(np.radians(deg)).tolist() == [5, 1, 3, 2, 6, 4]


@pytest.mark.parametrize("rpm, expect", [(60.0, [5, 1, 3, 2, 6, 4, 5]), (-60.0, [5, 4, 6, 2, 3, 1, 5])])
def test_hall_sequence_by_direction(rpm, expect):
    c = synthetic_capture(rpm=rpm, seconds=0.5, fs=5000.0, theta_r0=0.1)
    assert _sequence(c["hall"])[:7] == expect
    validate(c)


@pytest.mark.parametrize("rpm", [60.0, -45.0, 300.0])
def test_events_exact_and_consistent_with_levels(rpm):
    c = synthetic_capture(rpm=rpm, seconds=0.4, fs=5000.0, theta_r0=0.37)
    P, N = 6, 64
    omega_r = rpm * 2 * np.pi / 60 * P / 2
    for name in ("enc_a", "enc_b", "hall"):
        times, levels = c.events[name]
        assert np.all(np.diff(times) > 0) and np.all(times > 0) and np.all(times <= c.t[-1])
        levels_from_events = zoh(np.r_[0.0, times], np.r_[c[name][0], levels], c.t)
        assert np.array_equal(levels_from_events, c[name])
    # hall edges lie exactly on multiples of 60 electrical degrees
    theta = 0.37 + omega_r * c.events["hall"][0]
    assert np.allclose(np.mod(theta / (np.pi / 3) + 0.5, 1.0) - 0.5, 0.0, atol=1e-9)
    # A goes high at multiples of the pulse pitch in forward rotation (half a pitch later in
    # reverse, where its high half is entered from the other side); B a quarter pitch after A
    shift = 0.0 if rpm > 0 else 0.5
    for name, offset in (("enc_a", 0.0), ("enc_b", 0.25)):
        times, levels = c.events[name]
        x = (0.37 + omega_r * times[levels == 1]) * N / (np.pi * P) - offset - shift
        assert np.allclose(x, np.round(x), atol=1e-9), name


def test_a_leads_b_in_forward_rotation():
    c = synthetic_capture(rpm=60.0, seconds=0.2, fs=20000.0)
    a_rise = c.events["enc_a"][0][c.events["enc_a"][1] == 1]
    b_rise = c.events["enc_b"][0][c.events["enc_b"][1] == 1]
    pitch = 60.0 / (60.0 * 64)  # s per pulse at 60 rpm
    # A rises at t = 0 (the start level, no event), B first a quarter pitch later: pair A's k-th
    # recorded rise with B's (k+1)-th
    n = min(len(a_rise), len(b_rise) - 1)
    lag = b_rise[1 : n + 1] - a_rise[:n]
    assert np.allclose(lag, pitch / 4, rtol=1e-9)


def test_quantisation_ripple_is_paper_eq_11():
    """Without ripple terms and noise the torque is kt*i_qo*cos(dtheta): p-p = eq. (11), 4.3 % at 64 PPR."""
    c = synthetic_capture(k6=0.0, c6=0.0, noise=0.0, torque_lsb=0.0, fs=200000.0, seconds=0.1)
    T = c["torque"]
    T_e = KT * 65.0
    assert T.max() == pytest.approx(T_e, rel=1e-12)
    eta = 100 * (T.max() - T.min()) / T_e
    assert eta == pytest.approx(100 * (1 - np.cos(6 * np.pi / 64)), rel=1e-3)
    assert 4.25 < eta < 4.35


def test_ripple_terms_sign_and_phase():
    base = synthetic_capture(k6=0.0, c6=0.0, torque_lsb=0.0, seconds=0.2)
    with_k6 = synthetic_capture(k6=0.00062, phase_k6=0.3, c6=0.0, torque_lsb=0.0, seconds=0.2)
    with_c6 = synthetic_capture(k6=0.0, c6=0.004, phase_c6=1.1, torque_lsb=0.0, seconds=0.2)
    theta = 2 * np.pi * 60 / 60 * 3 * base.t  # electrical angle, theta_r0 = 0
    assert np.allclose(with_k6["torque"] - base["torque"], -0.00062 * 65.0 * np.sin(6 * theta + 0.3), atol=1e-12)
    assert np.allclose(with_c6["torque"] - base["torque"], -0.004 * np.sin(6 * theta + 1.1), atol=1e-12)


def test_deterministic_and_truth_set():
    a, b = synthetic_capture(seed=4, seconds=0.3), synthetic_capture(seed=4, seconds=0.3)
    assert np.array_equal(a["torque"], b["torque"])
    assert not np.array_equal(a["torque"], synthetic_capture(seed=5, seconds=0.3)["torque"])
    assert a.truth["k6"] == 0.00062 and a.truth["seed"] == 4
    assert "k6" not in a.metadata and a.metadata["poles"] == 6 and a.metadata["encoder_ppr"] == 64
    # the transducer resolution quantises torque to 1e-5 N*m
    assert np.allclose(a["torque"] / 1e-5, np.round(a["torque"] / 1e-5), atol=1e-6)
