"""Standstill is an absolute speed, not a fraction of the capture's top speed: one continuous
capture from 60 to 1500 rpm keeps its slow windows (issue 34's bug in ``direction_pieces``)."""

from __future__ import annotations

import numpy as np
import pytest

from eol_cal.analysis.fit.capture import capture_angle, capture_segments
from eol_cal.analysis.steady import direction_pieces
from eol_cal.plant.presets import paper
from eol_cal.plant.profile import Profile, ProfileSegment
from eol_cal.plant.simulate import simulate


def test_one_continuous_capture_keeps_its_60_rpm_window_beside_1500_rpm():
    prof = Profile("60-1500", (ProfileSegment(60.0, 1.0, iq=40.0), ProfileSegment(1500.0, 0.4, iq=40.0, ramp_s=0.1)))
    cap = simulate(paper(), prof, mode="estimated", seed=1)[0].capture
    ang = capture_angle(cap)
    segs = capture_segments(cap.t, ang.theta_r, ang.omega_r, np.asarray(cap.iq_ref(), dtype=float))
    pole_pairs = cap.poles // 2
    rpm = [float(ang.theta_r[b - 1] - ang.theta_r[a]) / float(cap.t[b - 1] - cap.t[a]) / pole_pairs * 60 / (2 * np.pi)
           for a, b in segs]
    assert any(abs(r - 60.0) < 3.0 for r in rpm), rpm
    assert any(abs(r - 1500.0) < 30.0 for r in rpm), rpm


def test_standstill_and_reversal_still_split_the_pieces():
    # 0.2 s forward at 19 rad/s (60 rpm with 3 pole pairs), standstill, 0.2 s reverse at 800 rad/s
    w = np.concatenate([np.full(2000, 19.0), np.zeros(500), np.full(2000, -800.0)])
    assert direction_pieces(w) == [(0, 2000), (2500, 4500)]


def test_the_units_spans_in_two_reductions_are_each_units_ptp():
    from eol_cal.analysis.steady import _spans

    rng = np.random.default_rng(5)
    for _ in range(50):
        x = rng.normal(size=int(rng.integers(10, 3000)))
        b = np.unique(rng.integers(0, len(x) + 1, int(rng.integers(2, 40))))
        if len(b) < 2:
            continue
        assert np.array_equal(_spans(x, b), np.array([np.ptp(x[b[k]:b[k + 1]]) for k in range(len(b) - 1)]))
    with pytest.raises(ValueError):  # an empty unit, as np.ptp
        _spans(np.arange(5.0), np.array([0, 2, 2, 4]))
