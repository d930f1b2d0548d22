"""Offline angle reconstruction against analytic motions with a known truth."""

import numpy as np
import pytest
from _analysis_motion import levels_from_angle, motion_capture

from eol_cal.analysis.angle import (
    NOMINAL_HALL_ANGLES,
    capture_angle,
    hall_transition_angles,
    reconstruct_angle,
)
from eol_cal.capture.data import Capture
from eol_cal.numerics.wrap import wrap_pi
from eol_cal.errors import InputError

FS = 20000.0
T = np.arange(0.0, 2.0, 1.0 / FS)


def _error_deg(result, theta_m, poles=6, t=T):
    err = wrap_pi(result.theta_r - poles / 2 * theta_m)
    inside = (t >= result.t_span[0]) & (t <= result.t_span[1])
    return np.rad2deg(np.abs(err[inside]))


def test_nominal_hall_angles_match_contract():
    # contract: state 1..6 begins at 60, 180, 120, 300, 0, 240 deg
    assert np.allclose(np.rad2deg(NOMINAL_HALL_ANGLES), [60, 180, 120, 300, 0, 240])
    angle, direction = hall_transition_angles(np.array([4, 5, 1, 5, 1]), np.array([5, 1, 5, 4, 2]))
    assert np.allclose(np.rad2deg(angle[:4]), [0, 60, 60, 0])
    assert list(direction) == [1, 1, -1, -1, 0]
    assert np.isnan(angle[4])


@pytest.mark.parametrize(
    "name, theta_m",
    [
        ("60 rpm", 2 * np.pi * 1.0 * T + 0.3),
        # the paper's Fig. 9(b): 30 rpm accelerating towards 85 rpm
        ("ramp 30..85 rpm", 2 * np.pi * (0.5 * T + 0.5 * (55 / 60 / 2.0) * T**2) + 1.1),
        ("reverse 60 rpm", -2 * np.pi * 1.0 * T + 0.3),
    ],
)
@pytest.mark.parametrize("with_b", [True, False])
def test_angle_error_far_below_encoder_step(name, theta_m, with_b):
    cap = motion_capture(T, theta_m, phi_enc=0.0123, with_b=with_b)
    res = capture_angle(cap)
    err = _error_deg(res, theta_m)
    step_deg = np.rad2deg(res.edge_step_rad)
    assert step_deg == pytest.approx(4.21875 if with_b else 8.4375)
    assert err.max() < 0.02 * step_deg, (name, err.max())
    assert res.n_edges == pytest.approx((4 if with_b else 2) * 64 * abs(theta_m[-1] - theta_m[0]) / (2 * np.pi), abs=2)
    assert res.direction == (-1 if theta_m[-1] < theta_m[0] else 1)
    true_rpm = (theta_m[-1] - theta_m[0]) / (T[-1] - T[0]) * 60 / (2 * np.pi)
    assert res.speed_rpm == pytest.approx(true_rpm, rel=0.02)
    assert np.rad2deg(res.hall_residual_max_rad) < 0.2


def test_speed_follows_the_ramp():
    accel = 55 / 60 / 2.0  # rev/s^2
    theta_m = 2 * np.pi * (0.5 * T + 0.5 * accel * T**2)
    res = capture_angle(motion_capture(T, theta_m))
    omega_true = 3 * 2 * np.pi * (0.5 + accel * T)
    inside = (T > res.t_span[0]) & (T < res.t_span[1])
    assert np.max(np.abs(res.omega_r[inside] / omega_true[inside] - 1)) < 0.02


def test_hall_placement_errors_average_out_in_the_offset():
    rng = np.random.default_rng(7)
    hall_err = rng.uniform(-3.0, 3.0, 6)
    theta_m = 2 * np.pi * 1.0 * T + 0.7
    res = capture_angle(motion_capture(T, theta_m, phi_enc=0.031, hall_err_deg=hall_err))
    # every transition is weighted equally, so the bias is the mean placement error
    err = np.rad2deg(wrap_pi(res.theta_r - 3 * theta_m))
    inside = (T >= res.t_span[0]) & (T <= res.t_span[1])
    assert abs(np.mean(err[inside]) + np.mean(hall_err)) < 0.05
    assert np.rad2deg(res.hall_residual_max_rad) == pytest.approx(np.max(np.abs(hall_err - hall_err.mean())), abs=0.1)


def test_exact_event_times_beat_sample_midpoints():
    fs_coarse, fine = 2000.0, 50
    t = np.arange(0.0, 2.0, 1.0 / fs_coarse)
    tf = np.arange(0.0, 2.0, 1.0 / (fs_coarse * fine))
    speed = 2 * np.pi * 1.3
    a, b, hall = levels_from_angle(speed * t + 0.2)
    af, bf, hf = levels_from_angle(speed * tf + 0.2)

    def ev(x):
        i = np.flatnonzero(x[1:] != x[:-1]) + 1
        return 0.5 * (tf[i - 1] + tf[i]), x[i]

    meta = {"serial": "E", "poles": 6, "encoder_ppr": 64}
    plain = Capture(t=t, channels={"enc_a": a, "enc_b": b, "hall": hall}, metadata=meta)
    evented = Capture(t=t, channels={"enc_a": a, "enc_b": b, "hall": hall}, metadata=meta,
                      events={"enc_a": ev(af), "enc_b": ev(bf), "hall": ev(hf)})
    e_plain = _error_deg(capture_angle(plain), speed * t + 0.2, t=t)
    e_event = _error_deg(capture_angle(evented), speed * t + 0.2, t=t)
    assert e_event.max() < 0.25 * e_plain.max()
    assert e_event.max() < 0.01


def test_bad_inputs_are_refused_with_the_channel_named():
    theta_m = 2 * np.pi * T
    a, b, hall = levels_from_angle(theta_m)
    hall_bad = hall.copy()
    hall_bad[1000] = 7
    with pytest.raises(InputError) as exc:
        reconstruct_angle(T, a, hall_bad, 6, 64, enc_b=b, source="x.csv")
    assert exc.value.field == "hall" and exc.value.file == "x.csv" and "7" in exc.value.reason
    with pytest.raises(InputError) as exc:
        reconstruct_angle(T, np.zeros_like(a), hall, 6, 64, enc_b=b)
    assert exc.value.field == "enc_a"
    # B wired as A's inverse lead: the quadrature says reverse while the halls say forward
    with pytest.raises(InputError) as exc:
        reconstruct_angle(T, b, hall, 6, 64, enc_b=a)
    assert exc.value.field == "enc_b" and "contradicts" in exc.value.reason
    cap = Capture(t=T, channels={"enc_a": a}, metadata={"serial": "s", "poles": 6, "encoder_ppr": 64})
    with pytest.raises(InputError) as exc:
        capture_angle(cap)
    assert exc.value.field == "hall"


@pytest.mark.parametrize("where", ["just after an A edge", "in the sample of a B edge", "mid-cell"])
def test_single_sample_glitches_on_a_are_collapsed(where):
    theta_m = 2 * np.pi * T + 0.3
    a, b, hall = levels_from_angle(theta_m)
    ea, eb = np.flatnonzero(np.diff(a)), np.flatnonzero(np.diff(b))
    idx = {"just after an A edge": ea[50] + 3, "in the sample of a B edge": eb[80] + 1,
           "mid-cell": (ea[90] + eb[90]) // 2}[where]
    a[idx] ^= 1
    kept = reconstruct_angle(T, a, hall, 6, 64, enc_b=b, bounce_frac=0.0)
    res = reconstruct_angle(T, a, hall, 6, 64, enc_b=b)
    assert _error_deg(res, theta_m).max() < 0.15
    assert _error_deg(kept, theta_m).max() > 0.5  # without the debounce the glitch shows
    assert np.rad2deg(res.hall_residual_max_rad) < 0.15  # no count slip


def test_reversal_inside_the_record():
    theta_m = 2 * np.pi * (T - 0.5 * T**2) + 0.3  # 60 rpm forward, turning at t = 1 s, 60 rpm back
    res = capture_angle(motion_capture(T, theta_m))
    err = _error_deg(res, theta_m)
    inside = (T >= res.t_span[0]) & (T <= res.t_span[1])
    away = np.abs(T[inside] - 1.0) > 0.1
    assert res.direction == 0
    assert err[away].max() < 0.1
    assert err.max() < np.rad2deg(res.edge_step_rad) / 2  # at the turn: within the cell


def test_hall_table_inputs_only_where_the_edges_say_the_angle():
    # the encoder toggles only between 0.8 and 1.25 s (one hall boundary, state 3 at 120 deg, in
    # that span); two more transitions outside it still anchor the offset, but their angle is
    # extrapolated, so they are not handed to the hall table measurement (analysis.halls)
    theta_m = 2 * np.pi * 0.1 * T + 0.05
    cap = motion_capture(T, theta_m)
    i0, i1 = np.flatnonzero((T >= 0.8) & (T <= 1.25))[[0, -1]]
    for ch in ("enc_a", "enc_b"):
        x = cap.channels[ch]
        x[:i0], x[i1:] = x[i0], x[i1]
    res = capture_angle(cap)
    assert res.n_hall_edges == 3
    assert list(res.hall_begins) == [3] and len(res.hall_theta) == 1
    assert np.rad2deg(res.hall_theta[0]) == pytest.approx(120.0, abs=0.5)


def test_nominal_transitions_kept_by_the_angle_are_hall_transitions():
    """angle.nominal_transitions: what capture_angle kept (AngleResult.hall_events) gives the hall
    transitions at the nominal angles bit for bit, as hall_transitions finds them again (the
    fingerprint's hall orders read them; issue 37: found once a capture, not twice)."""
    import dataclasses

    import numpy as np

    from eol_cal.analysis.angle import capture_angle, hall_transitions, nominal_transitions
    from eol_cal.capture.synthetic import synthetic_capture

    c = synthetic_capture(rpm=-120.0, i_qo=20.0, seconds=0.2, seed=3)
    ang = capture_angle(c)
    want = hall_transitions(np.asarray(c.t, dtype=float), c["hall"], c.events.get("hall"), source=c.source)
    for a in (ang, dataclasses.replace(ang, hall_events=None)):  # kept, and found again where not kept
        got = nominal_transitions(c, a)
        assert all(np.array_equal(g, w) and g.dtype == w.dtype for g, w in zip(got, want, strict=True))
