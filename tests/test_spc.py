"""SPC definitions against textbook answers: the minimum-n rule, circular statistics across the
wrap in closed form, frozen control lines, and a series that fires each of Nelson's rules judged
1-4 (and one that fires none)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.lot.spc import (RULES, circular_capability, circular_histogram, circular_summary, freeze_line, gate,
                             gated_capability, judge, n_reason, run_rules, wrapped_deviation)
from eol_cal.numerics.wrap import wrap_pi

DEG = math.pi / 180.0


# --------------------------------------------------------------------------- minimum n
def test_min_n_gives_the_value_or_the_reason():
    assert n_reason(7, 25) == "n = 7 < 25" and n_reason(25, 25) is None
    assert gate(1.94, 3).value is None and gate(1.94, 3).reason == "n = 3 < 25" and gate(1.94, 3).n == 3
    assert gate(1.94, 25).value == 1.94 and gate(1.94, 25).reason is None
    assert gate(math.nan, 30, undefined="no spread").reason == "no spread"
    assert gate(1.0, 3).text() == "n = 3 < 25" and gate(1.2345, 30).text() == "1.23"


def test_capability_is_gated_by_n():
    x = [1.0, 3.0, 2.0, 4.0, 3.0]  # the hand-worked lot of test_lot_stats: Cpk 0.852267 against USL 6
    few = gated_capability(x, None, 6.0)
    assert few["cpk"].value is None and few["cpk"].reason == "n = 5 < 25"
    enough = gated_capability(x, None, 6.0, min_n=5)
    assert enough["cpk"].value == pytest.approx(3.4 / (3 * 1.5 / 1.128), abs=1e-9)
    assert enough["cp"].value is None and enough["cp"].reason == "needs both limits"
    flat = gated_capability([2.0] * 30, 0.0, 3.0)
    assert flat["cpk"].reason == "no spread (all values equal)"
    noisy = gated_capability([0.8] * 30, 0.3, None)  # their mean is not 0.8 to the last bit: still no spread
    assert noisy["ppk"].value is None and noisy["ppk"].reason == "no spread (all values equal)"


# --------------------------------------------------------------------------- circular
def test_circular_mean_and_sd_across_the_wrap_in_closed_form():
    # 160, 170, 190, 200 deg: symmetric about 180 deg, so the mean is pi; the unit vectors'
    # mean length is R = (2 cos 10 deg + 2 cos 20 deg) / 4; the circular sd sqrt(-2 ln R)
    theta = np.array([160.0, 170.0, -170.0, -160.0]) * DEG
    s = circular_summary(theta)
    r = (2 * math.cos(10 * DEG) + 2 * math.cos(20 * DEG)) / 4
    assert abs(wrap_pi(s.mean - math.pi)) < 1e-12
    assert s.resultant == pytest.approx(r, rel=1e-12)
    assert s.sd == pytest.approx(math.sqrt(-2 * math.log(r)), rel=1e-12)
    assert s.sd / DEG == pytest.approx(15.895, abs=1e-3)  # the linear sd of the same numbers: 190.6 deg
    assert np.std(theta / DEG, ddof=1) == pytest.approx(190.6, abs=0.1)
    # the same definitions as scipy's (circstd is sqrt(-2 ln R))
    import scipy.stats  # ~1 s to import: in the test, not in every worker's collection

    assert abs(wrap_pi(s.mean - scipy.stats.circmean(theta, high=math.pi, low=-math.pi))) < 1e-12
    assert s.sd == pytest.approx(scipy.stats.circstd(theta, high=math.pi, low=-math.pi), rel=1e-12)
    # three angles: 170, 180, -170 deg -> mean pi, R = (1 + 2 cos 10 deg) / 3
    t3 = circular_summary(np.array([170.0, 180.0, -170.0]) * DEG)
    assert abs(wrap_pi(t3.mean - math.pi)) < 1e-12 and t3.resultant == pytest.approx((1 + 2 * math.cos(10 * DEG)) / 3)
    # opposite angles cancel: no mean, infinite sd; none: NaN
    zero = circular_summary([0.0, math.pi])
    assert math.isnan(zero.mean) and math.isinf(zero.sd)
    assert circular_summary([math.nan]).count == 0


def test_circular_histogram_counts_each_angle_once():
    theta = np.array([-math.pi, math.pi, 179.0 * DEG, -179.0 * DEG, 0.0, 1.0 * DEG, math.nan])
    counts, edges = circular_histogram(theta, bins=4)
    assert edges[0] == -math.pi and edges[-1] == math.pi and len(edges) == 5
    assert counts.tolist() == [3, 0, 2, 1]  # -pi, pi (one angle) and -179 deg; 0 and 1 deg; 179 deg
    assert counts.sum() == 6


def test_phase_capability_on_the_wrapped_deviation():
    # a phase at 180 deg +- 2 deg (around the wrap) against 180 +- 10 deg: the deviations are
    # -2, 2, -2, 2 ... deg: mean 0, MRbar 4 deg, sigma_within 4 / 1.128 deg
    theta = np.array([178.0 if i % 2 else -178.0 for i in range(30)]) * DEG
    dev = wrapped_deviation(theta, math.pi)
    assert np.allclose(np.abs(dev), 2 * DEG)
    c = circular_capability(theta, math.pi, 10 * DEG, 10 * DEG)
    sigma_w = 4 * DEG / 1.128
    assert c.cp == pytest.approx(20 * DEG / (6 * sigma_w)) and c.cpk == pytest.approx(10 * DEG / (3 * sigma_w))
    with pytest.raises(ValueError):
        circular_capability(theta, 0.0, 0.0, 1.0)


# --------------------------------------------------------------------------- frozen lines
def test_freeze_line_by_hand_and_below_min_n():
    x = [1.0, 3.0, 2.0, 4.0, 3.0]  # mean 2.6, MRbar 1.5
    line = freeze_line(x, min_n=5)
    assert line.center == pytest.approx(2.6) and line.sigma == pytest.approx(1.5 / 1.128)
    assert line.ucl == pytest.approx(2.6 + 3 * 1.5 / 1.128) and line.mr_ucl == pytest.approx(3.267 * 1.5)
    short = freeze_line(x)
    assert short.center is None and short.ucl is None and short.reason == "n = 5 < 25"
    assert judge([100.0], short) == []
    assert freeze_line([2.0] * 30).reason == "no spread (all values equal)"


def test_freeze_line_of_a_phase_across_the_wrap():
    # 179, -179, 179, ... deg: circular mean 180 deg, wrapped moving ranges 2 deg (not 358)
    theta = np.array([179.0 if i % 2 == 0 else -179.0 for i in range(26)]) * DEG
    line = freeze_line(theta, circular=True)
    assert abs(wrap_pi(line.center - math.pi)) < 1e-12
    assert line.mr_center == pytest.approx(2 * DEG) and line.sigma == pytest.approx(2 * DEG / 1.128)
    # 3 sigma = 5.32 deg: 185 deg (5 deg off) is within, -170 deg (190 deg: 10 deg off, above) beyond
    assert judge(np.array([185.0]) * DEG, line) == []
    v = judge(np.array([-170.0]) * DEG, line, "phase_c6")
    assert [(x.rule, x.side, x.runs, x.quantity) for x in v] == [(1, 1, (0,), "phase_c6")]


# --------------------------------------------------------------------------- run rules
def fired(x, center=0.0, sigma=1.0):
    return [(v.rule, v.side, v.runs) for v in run_rules(x, center, sigma, "k6")]


QUIET = [0.5, -0.5, 0.8, -0.9, 0.2, -0.1, 1.5, -1.2, 0.3, -0.4, 2.5, -0.6, 0.7, -0.8, 0.9, -1.1, 0.4, -0.2]


def test_a_series_within_control_fires_no_rule():
    # alternating sides (no run of 8), one lone point beyond 2 sigma, never two 1-sigma points in 5 on one side
    assert fired(QUIET) == []


def test_rule_1_one_point_beyond_3_sigma():
    x = [0.5, -0.5, 0.2, -3.5, 0.1, -0.3]
    assert fired(x) == [(1, -1, (3,))]


def test_nelson_5_two_of_three_beyond_2_sigma_on_one_side():
    x = [0.5, -0.5, 2.5, 0.1, 2.2, -0.3, 0.4, -0.6]
    assert fired(x) == [(5, 1, (2, 4))]
    # on opposite sides it is not the pattern
    assert fired([0.5, -0.5, 2.5, 0.1, -2.2, -0.3]) == []


def test_nelson_6_four_of_five_beyond_1_sigma_on_one_side():
    x = [0.5, -0.5, -1.5, -1.2, -0.5, -1.8, -1.1, 0.3, -0.4, 0.6]
    assert fired(x) == [(6, -1, (2, 3, 5, 6))]


def test_nelson_2_nine_in_a_row_on_one_side():
    x = [-0.5, 0.3, 0.5, 0.1, 0.9, 0.2, 0.4, 0.6, 0.7, 0.2, -0.5]
    assert fired(x) == [(2, 1, (1, 2, 3, 4, 5, 6, 7, 8, 9))]
    # eight in a row is not (the Western Electric rule 4 was: Nelson's needs nine); a point on the centre line breaks it
    assert fired([-0.5, 0.5, 0.4, *[0.5, 0.4] * 3, -0.5]) == []
    assert fired([*[0.5, 0.4] * 2, 0.0, *[0.5, 0.4] * 3]) == []


def test_nelson_3_the_trend_six_rising_or_falling_in_a_row():
    """A steady climb inside the limits is a trend from its sixth point: the rule the Western
    Electric set had not (a 20-run climb showed only as '8 in a row' twice)."""
    climb = np.linspace(-1.4, 1.4, 20)
    got = fired(climb)
    assert (3, 1, tuple(range(20))) in got
    assert fired([0.1, 0.3, 0.2, 0.4, 0.5, 0.6, 0.7, 0.8, -0.5]) == [(3, 1, (2, 3, 4, 5, 6, 7))]
    assert fired([0.5, 0.4, 0.3, 0.2, 0.1, 0.0, -0.1, 0.3]) == [(3, -1, (0, 1, 2, 3, 4, 5, 6))]
    # five rising, or a tie inside the run, is not a trend
    assert fired([0.1, 0.2, 0.3, 0.4, 0.5, -0.2]) == []
    assert fired([0.1, 0.2, 0.3, 0.3, 0.4, 0.5, 0.6, -0.2]) == []


def test_rules_against_a_frozen_centre_and_sigma_skip_missing_values():
    # centre 10, sigma 0.2: 11 is beyond 3 sigma; the NaN (a run without the value) is not a point
    x = [10.1, math.nan, 9.9, 11.0, 10.05]
    assert fired(x, 10.0, 0.2) == [(1, 1, (3,))]
    # overlapping windows of one pattern are one violation: ten in a row above
    long = [-0.5, *[0.5, 0.4] * 5, -0.5]
    assert fired(long) == [(2, 1, tuple(range(1, 11)))]
    # two points in a row beyond 3 sigma are one violation of rule 1; with one between, two
    assert fired([0.1, 3.2, 3.5, 0.2]) == [(1, 1, (1, 2)), (5, 1, (1, 2))]
    assert [v[:2] for v in fired([3.2, 0.1, 3.5])] == [(1, 1), (5, 1), (1, 1)]
    v = run_rules(long, 0.0, 1.0, "pp_after_pct")[0]
    assert v.quantity == "pp_after_pct" and v.text == "rule 2: " + RULES[2][3] + " (above)"
    with pytest.raises(ValueError):
        run_rules(x, 10.0, 0.0)


def test_a_drift_is_flagged_against_the_baseline_and_not_against_its_own_limits():
    rng = np.random.default_rng(21)
    base = 1.0 + 0.05 * rng.standard_normal(40)
    line = freeze_line(base)
    drifting = 1.0 + 0.05 * rng.standard_normal(40) + np.linspace(0.0, 0.25, 40)
    assert any(v.rule in RULES for v in judge(drifting, line))
    assert line.center == pytest.approx(float(base.mean()))
