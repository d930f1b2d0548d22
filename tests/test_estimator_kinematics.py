"""The kinematic encoder/hall signal model against the contract's conventions."""

from __future__ import annotations

import math

import numpy as np

from eol_cal.firmware.kinematics import (SensorErrors, draw_sensor_errors, electrical_angle,
                                         encoder_hall_signals, ideal_sensor_errors, speed_profile_angle)


def _rises(x):
    return np.flatnonzero((x[1:] == 1) & (x[:-1] == 0)) + 1


def test_ideal_encoder_pulses_and_quadrature():
    theta = np.linspace(0.0, 2 * math.pi, 64 * 400, endpoint=False)
    a, b, h = encoder_hall_signals(theta, 6, 64)
    ra, rb = _rises(a), _rises(b)
    assert len(ra) == 63 and a[0] == 1  # pulse 0 starts at 0: 64 pulses, the first at sample 0
    assert np.allclose(np.diff(ra), 400) and np.mean(a) == 0.5
    # forward: A leads B by a quarter pitch (100 samples)
    assert np.all(rb[:10] - ra[:10] == 100) or np.all(rb[:10] - np.r_[0, ra[:9]] == 100)


def test_hall_sequence_and_nominal_angles():
    theta_e = np.radians(np.arange(0.0, 360.0, 0.25))
    a, b, h = encoder_hall_signals(theta_e / 3.0, 6, 64)
    changes = np.flatnonzero(np.diff(h)) + 1
    states = [int(h[0])] + [int(h[i]) for i in changes]
    assert states == [5, 1, 3, 2, 6, 4]  # contract: forward 5 -> 1 -> 3 -> 2 -> 6 -> 4
    assert np.allclose(np.degrees(theta_e[changes]), [60, 120, 180, 240, 300])
    assert set(np.unique(h)) == {1, 2, 3, 4, 5, 6}


def test_errors_move_the_edges_by_their_amount():
    edge = np.zeros(64)
    edge[3] = math.radians(0.1)
    hall = np.zeros((3, 2))
    hall[0, 1] = math.radians(1.5)  # U falls 1.5 electrical degrees late
    err = SensorErrors(edge, hall, 0.0)
    theta = np.radians(np.arange(0.0, 360.0, 0.001))
    a0, _, h0 = encoder_hall_signals(theta, 6, 64)
    a1, _, h1 = encoder_hall_signals(theta, 6, 64, err)
    d = np.flatnonzero(a0 != a1)
    # pulse 3 (rising at 16.875 deg mech) shifted by 0.1 deg: 100 samples at each of its edges
    assert len(d) == 200 and abs(np.degrees(theta[d[0]]) - 16.875) < 0.002
    dh = np.flatnonzero(h0 != h1)
    assert len(dh) == 3 * 500  # U falls at 180 deg elec: 3 times a mechanical turn, 0.5 deg mech each
    assert abs(np.degrees(theta[dh[0]]) * 3 - 180.0) < 0.01


def test_draw_sensor_errors_bounds():
    err = draw_sensor_errors(np.random.default_rng(0), 64)
    assert err.edge_error.shape == (64,) and err.hall_offset.shape == (3, 2)
    assert np.std(np.degrees(err.edge_error)) < 0.2
    assert np.max(np.abs(np.degrees(err.hall_offset))) <= 2.0
    assert 0.0 <= err.grid_offset < 2 * math.pi / 64
    assert ideal_sensor_errors(64).edge_error.shape == (64,)


def test_speed_profile_angle_is_exact():
    th = speed_profile_angle(((1.0, 60.0, 60.0), (2.0, 60.0, 120.0)), 1000.0, 0.5)
    assert len(th) == 3000
    assert abs(th[999] - (0.5 + 2 * math.pi * 0.999)) < 1e-12
    # ramp: mean speed 90 rpm over 2 s = 3 revolutions
    end = 0.5 + 2 * math.pi + 2 * math.pi * 3.0
    assert abs((th[-1] + (th[-1] - th[-2])) - end) < 1e-5
    assert np.all(electrical_angle(th, 6) < 2 * math.pi)
