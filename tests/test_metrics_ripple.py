"""Ripple index eta and the steady-window peak-to-peak ripple on signals with known answers."""

import numpy as np
import pytest
from _analysis_motion import motion_capture

from eol_cal.analysis.metrics import capture_ripple_pp, eta_percent, hampel, ripple_pp
from eol_cal.errors import InputError

FS = 20000.0
T = np.arange(0.0, 3.0, 1.0 / FS)
THETA = 3 * 2 * np.pi * 1.0 * T + 0.3  # 60 rpm, 6 poles: electrical angle (rad)
T_AVG, A6 = 3.2, 0.05
CLEAN = T_AVG + A6 * np.sin(6 * THETA + 0.4)
TRUE_PCT = 100 * 2 * A6 / T_AVG  # 3.125 %


def test_eta_matches_the_paper():
    assert eta_percent(64, 6) == pytest.approx(4.3, abs=0.01)
    assert eta_percent(200, 6) == pytest.approx(0.44, abs=0.005)
    assert eta_percent(500, 6) < 0.1  # "above 500 PPR lower than 0.1 %"
    got = eta_percent(np.array([64, 200, 2048]), 6)
    assert got.shape == (3,) and got[0] > got[1] > got[2]
    assert np.allclose(eta_percent(np.array([64, 128]), np.array([[6], [8]])).shape, (2, 2))


def test_hampel_removes_spikes_and_leaves_smooth_signals():
    x = np.sin(np.linspace(0, 20, 4000))
    y, spikes = hampel(x, 10)
    assert not spikes.any() and np.array_equal(x, y)
    x2 = x.copy()
    x2[[500, 2000, 2001, 2002]] += 5.0
    y2, spikes2 = hampel(x2, 10)
    assert set(np.flatnonzero(spikes2)) == {500, 2000, 2001, 2002}
    assert np.max(np.abs(y2 - x)) < 0.02  # the median of a slope, 3 of 21 samples hit


def test_hampel_equals_its_definition_window_by_window():
    from numpy.lib.stride_tricks import sliding_window_view

    rng = np.random.default_rng(5)
    x = CLEAN[:20000] + 0.005 * rng.standard_normal(20000)
    x[rng.choice(20000, 30, replace=False)] += rng.choice([-0.2, 0.2], 30)
    k = 10
    win = sliding_window_view(np.pad(x, k, mode="reflect"), 2 * k + 1)
    m = np.median(win, axis=1)
    mad = np.median(np.abs(win - m[:, None]), axis=1)
    d = np.abs(np.diff(x))
    floor = max(1.4826 * np.median(d) / np.sqrt(2), d[d > 0].min())
    want = np.abs(x - m) > 3.0 * np.maximum(1.4826 * mad, floor)
    y, spikes = hampel(x, k)
    assert np.array_equal(spikes, want) and spikes.sum() >= 30
    assert np.array_equal(y, np.where(want, m, x))


def test_hampel_leaves_the_lsb_flicker_of_a_quantised_signal():
    rng = np.random.default_rng(3)
    lsb = 1e-3
    x = np.round((3.2 + 0.0004 * rng.standard_normal(20000)) / lsb) * lsb  # flat, +-1 LSB flicker
    y, spikes = hampel(x, 10)
    assert spikes.sum() == 0
    x[5000] += 0.05
    assert hampel(x, 10)[1].sum() == 1


def test_pp_of_a_sine_is_twice_its_amplitude_over_the_mean():
    r = ripple_pp(T, CLEAN, THETA, poles=6)
    assert r.raw_pct == pytest.approx(TRUE_PCT, abs=0.005)
    assert r.filtered_pct == pytest.approx(TRUE_PCT, abs=0.005)
    assert r.T_avg_nm == pytest.approx(T_AVG, abs=1e-4)
    assert r.speed_rpm == pytest.approx(60.0, rel=1e-6)
    assert r.window_revs == 3  # one mechanical revolution
    # settle: the windows start 0.1 s after the run's start, whole revolutions from there
    assert r.windows[0].t_start == pytest.approx(0.1, abs=1e-3)
    assert len(r.windows) == 2  # 2.9 s usable: two whole mechanical revolutions
    assert all(w.t_end - w.t_start == pytest.approx(1.0, abs=1e-3) for w in r.windows)
    assert r.n_spikes == 0


def test_spikes_do_not_count():
    x = CLEAN.copy()
    x[30000] += 1.0
    x[45000:45004] -= 0.8
    r = ripple_pp(T, x, THETA, poles=6)
    assert r.raw_pct == pytest.approx(TRUE_PCT, abs=0.005)
    assert r.n_spikes >= 5


def test_noise_counts_raw_and_the_filter_removes_it():
    x = CLEAN + np.random.default_rng(0).normal(0.0, 0.01, len(T))
    r = ripple_pp(T, x, THETA, poles=6)
    assert r.raw_pct > TRUE_PCT + 1.0
    assert r.filtered_pct == pytest.approx(TRUE_PCT, abs=0.25)


def test_filter_keeps_the_orders_the_spectrum_reports():
    # orders 6..36 pass the cut-off at 48 x f_e nearly untouched; order 150 noise does not
    x = T_AVG + A6 * np.sin(6 * THETA) + 0.01 * np.sin(150 * THETA)
    r = ripple_pp(T, x, THETA, poles=6)
    base = ripple_pp(T, T_AVG + A6 * np.sin(6 * THETA), THETA, poles=6)
    assert r.filtered_pct == pytest.approx(base.filtered_pct, abs=0.01)
    assert r.raw_pct > base.raw_pct + 0.5


def test_windows_stay_inside_steady_load_points():
    t = np.arange(0.0, 6.0, 1.0 / FS)
    theta = 3 * 2 * np.pi * 1.0 * t
    i_qo = np.where(t < 3.05, 30.0, 65.0)
    kt = 0.049
    torque = kt * i_qo * (1 + 0.02 * np.sin(6 * theta))
    r = ripple_pp(t, torque, theta, poles=6, i_qo=i_qo)
    assert len(r.segments) == 2
    for w in r.windows:
        assert not (w.t_start < 3.05 < w.t_end)
        assert w.t_start >= 0.1 or w.t_start == 0.0
        assert w.raw_pct == pytest.approx(4.0, abs=0.01)
        assert w.T_avg_nm == pytest.approx(kt * w.i_qo_a, rel=1e-3)
    second = r.segments[1]
    assert second[0] >= 3.05 + 0.1  # settle time after the load step dropped
    assert {round(w.i_qo_a) for w in r.windows} == {30, 65}


def test_speed_change_splits_runs():
    t = np.arange(0.0, 5.0, 1.0 / FS)
    rps = np.where(t < 2.5, 1.0, 1.5)
    theta = 3 * 2 * np.pi * np.cumsum(rps) / FS
    r = ripple_pp(t, 3.0 + 0.03 * np.sin(6 * theta), theta, poles=6)
    assert {round(w.speed_rpm) for w in r.windows} == {60, 90}
    assert r.raw_pct == pytest.approx(2.0, abs=0.01)


def test_short_capture_uses_fewer_revolutions_and_too_short_is_refused():
    t = np.arange(0.0, 1.0, 1.0 / FS)
    theta = 3 * 2 * np.pi * t
    r = ripple_pp(t, 3.2 + 0.05 * np.sin(6 * theta), theta, poles=6)
    # 17 whole 60-degree units (0.944 s), 0.1 s settling: 2.5 revolutions, one window of two
    assert r.window_revs == 2 and len(r.windows) == 1
    assert r.windows[0].t_start == pytest.approx(0.1, abs=1e-3)
    assert r.raw_pct == pytest.approx(TRUE_PCT, abs=0.005)
    t = np.arange(0.0, 0.4, 1.0 / FS)
    theta = 3 * 2 * np.pi * t
    with pytest.raises(InputError) as exc:
        ripple_pp(t, 3.2 + 0 * t, theta, poles=6, source="short.csv")
    assert exc.value.file == "short.csv" and exc.value.field == "torque"
    with pytest.raises(InputError):
        ripple_pp(T, CLEAN, THETA, poles=6, window_revs=12)


def test_capture_level_uses_the_reconstructed_angle():
    cap = motion_capture(T, THETA / 3, torque=CLEAN)
    r = capture_ripple_pp(cap)
    assert r.raw_pct == pytest.approx(TRUE_PCT, abs=0.01)
    assert r.filtered_pct == pytest.approx(TRUE_PCT, abs=0.01)
    assert np.isfinite(r.windows[0].i_qo_a)


def test_each_run_keeps_its_own_window_length():
    # 0.9 s at 60 rpm, 0.1 s ramp, 0.8 s at 120 rpm (like the eol-default profile's points)
    t = np.arange(0.0, 1.8, 1.0 / FS)
    rps = np.interp(t, [0.0, 0.9, 1.0, 1.8], [1.0, 1.0, 2.0, 2.0])
    theta = 3 * 2 * np.pi * np.cumsum(rps) / FS
    r = ripple_pp(t, 3.0 + 0.03 * np.sin(6 * theta), theta, poles=6, i_qo=np.full(len(t), 60.0))
    by_speed = {round(w.speed_rpm): w.n_revs for w in r.windows}
    assert by_speed == {60: 2, 120: 3}
    assert r.window_revs == 3
    assert all(w.raw_pct == pytest.approx(2.0, abs=0.01) for w in r.windows)
    assert all(not (0.9 < w.t_end and w.t_start < 1.0) for w in r.windows)  # nothing from the ramp


def test_both_directions_in_one_capture():
    # 1.5 s at +60 rpm, 0.2 s reversal ramp, 1.5 s at -60 rpm
    t = np.arange(0.0, 3.2, 1.0 / FS)
    rps = np.interp(t, [0.0, 1.5, 1.7, 3.2], [1.0, 1.0, -1.0, -1.0])
    theta = 3 * 2 * np.pi * np.cumsum(rps) / FS
    r = ripple_pp(t, 3.0 + 0.03 * np.sin(6 * theta), theta, poles=6)
    assert {round(w.speed_rpm) for w in r.windows} == {60, -60}
    assert all(not (1.5 < w.t_end and w.t_start < 1.7) for w in r.windows)
    assert r.raw_pct == pytest.approx(2.0, abs=0.01)


def test_angle_error_at_the_encoder_order_does_not_break_a_steady_run():
    # 0.8 s at 120 rpm (an eol-default point): 4.8 electrical revolutions, 3 = one mechanical
    # revolution after the 0.1 s settling. An angle error of 1 deg (electrical) at mechanical
    # order 64 (a 64 PPR encoder's edges) moves the 60-degree unit boundaries by up to 3 % of a
    # unit; the shaft's speed is constant. Judged unit by unit against the run's first one, the
    # run broke, every piece lost another 0.1 s to settling and no window was left.
    t = np.arange(0.0, 0.8, 1.0 / FS)
    theta_true = 3 * 2 * np.pi * 2.0 * t
    theta = theta_true + np.radians(1.0) * np.sin(64 / 3 * theta_true)
    r = ripple_pp(t, 3.0 + 0.03 * np.sin(6 * theta_true), theta, poles=6, i_qo=np.full(len(t), 60.0))
    assert len(r.windows) == 1 and r.window_revs == 3
    assert r.segments[0][0] == pytest.approx(0.1, abs=0.03)
    assert r.raw_pct == pytest.approx(2.0, abs=0.01)


def test_a_speed_step_of_3_percent_still_ends_the_run():
    # 0.7 s at 120 rpm, then 123.6 rpm at the same i_qo, with the same encoder-order angle error
    t = np.arange(0.0, 1.4, 1.0 / FS)
    rps = np.where(t < 0.7, 2.0, 2.06)
    theta_true = 3 * 2 * np.pi * np.cumsum(rps) / FS
    theta = theta_true + np.radians(1.0) * np.sin(64 / 3 * theta_true)
    r = ripple_pp(t, 3.0 + 0.03 * np.sin(6 * theta_true), theta, poles=6, i_qo=np.full(len(t), 60.0))
    assert len(r.segments) == 2
    assert all(not (w.t_start < 0.7 < w.t_end) for w in r.windows)
    assert sorted(round(w.speed_rpm, 1) for w in r.windows) == [120.0, 123.6]


def test_no_mech1_takes_out_the_unbalance_and_leaves_the_electrical_ripple():
    # a 6th ripple plus a mechanical order 1 (unbalance) of a fifth of its size
    x = CLEAN + 0.2 * A6 * np.sin(THETA / 3 + 1.1)
    r = ripple_pp(T, x, THETA, poles=6)
    assert r.filtered_pct > TRUE_PCT + 0.3  # the unbalance counts in the p-p figure
    assert r.no_mech1_pct == pytest.approx(TRUE_PCT, abs=0.005)
    assert all(w.no_mech1_pct == pytest.approx(TRUE_PCT, abs=0.005) for w in r.windows)
    # without an unbalance it changes nothing
    assert ripple_pp(T, CLEAN, THETA, poles=6).no_mech1_pct == pytest.approx(TRUE_PCT, abs=0.005)


def test_no_mech1_over_part_of_a_mechanical_revolution():
    # the operating-point window of a 1 s capture at 60 rpm: two electrical revolutions, 240 mech. deg
    t = np.arange(0.0, 1.0, 1.0 / FS)
    theta = 3 * 2 * np.pi * t
    x = 3.2 + 0.05 * np.sin(6 * theta) + 0.01 * np.sin(theta / 3 + 0.5)
    r = ripple_pp(t, x, theta, poles=6)
    assert r.window_revs == 2
    assert r.no_mech1_pct == pytest.approx(TRUE_PCT, abs=0.05)
    # one electrical revolution (120 mech. deg) is too short an arc: not reported
    r1 = ripple_pp(t, x, theta, poles=6, window_revs=1)
    assert np.isnan(r1.no_mech1_pct) and all(np.isnan(w.no_mech1_pct) for w in r1.windows)
