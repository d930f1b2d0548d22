"""Lot statistics against values worked out by hand on a small lot."""

from __future__ import annotations

import math

import pytest

from eol_cal.sim.run_records import make_record
from eol_cal.lot.stats import capability, first_pass_yield, imr_limits, pareto, summary

# x in time order; mean 2.6, sd (ddof 1) sqrt(5.2 / 4) = 1.140175, moving ranges 2 1 2 1 -> MRbar 1.5
X = [1.0, 3.0, 2.0, 4.0, 3.0]


def test_summary_by_hand():
    s = summary(X + [math.nan])
    assert s.count == 5 and s.mean == pytest.approx(2.6) and s.sd == pytest.approx(1.140175, abs=1e-6)
    assert (s.minimum, s.maximum) == (1.0, 4.0) and s.percentiles[50.0] == 3.0
    assert s.percentiles[5.0] == pytest.approx(1.2)  # linear: 1 + 0.2 * (2 - 1)
    assert summary([]).count == 0 and math.isnan(summary([]).mean)


def test_capability_by_hand():
    c = capability(X, usl=6.0)  # sigma_within = 1.5 / 1.128 = 1.329787
    assert c.sigma_within == pytest.approx(1.329787, abs=1e-6)
    assert c.cpk == pytest.approx(3.4 / (3 * 1.329787), abs=1e-6)  # 0.852267
    assert c.ppk == pytest.approx(3.4 / (3 * 1.140175), abs=1e-6)  # 0.993999
    assert math.isnan(c.cp)  # one-sided
    both = capability(X, lsl=0.0, usl=6.0)
    assert both.cp == pytest.approx(6.0 / (6 * 1.329787), abs=1e-6)
    assert both.cpk == pytest.approx(2.6 / (3 * 1.329787), abs=1e-6)  # the lower side is nearer
    low = capability(X, lsl=2.0)
    assert low.cpk == pytest.approx(0.6 / (3 * 1.329787), abs=1e-6)
    assert math.isnan(capability([1.0], usl=2.0).cpk) and math.isnan(capability(X).cpk)
    flat = capability([2.0] * 4, lsl=0.0, usl=3.0)  # no spread: not defined, not a division by zero
    assert math.isnan(flat.cp) and math.isnan(flat.cpk) and math.isnan(flat.ppk)


def test_individuals_and_moving_range_limits_by_hand():
    lim = imr_limits(X)
    assert lim.center == pytest.approx(2.6) and lim.mr_center == pytest.approx(1.5)
    assert lim.ucl == pytest.approx(2.6 + 2.659574 * 1.5, abs=1e-5) and lim.lcl == pytest.approx(2.6 - 2.659574 * 1.5, abs=1e-5)
    assert lim.mr_ucl == pytest.approx(3.267 * 1.5)
    assert lim.beyond([2.0, 7.0, -2.0]) == [1, 2]


def rec(serial, t, **kw):
    return make_record(serial, started=f"2026-11-22T{t:02d}:00:00.000+00:00", **kw)


def test_first_pass_yield_and_pareto_by_hand():
    recs = [rec("A", 8),
            rec("B", 9, pp_after=2.5),  # fails max_pp_after_pct and min_improvement_pct (from the demo's 2.93 %)
            rec("B", 12),  # B's re-test passes: not a first pass
            rec("C", 10, error_step="acquire"),
            rec("D", 11, pp_after=1.9, pp_before=6.5),  # fails max_pp_before_pct (improvement 71 %)
            rec("E", 13, r2=0.2),  # fails min_r2
            rec("F", 7, refused=("wrong_serial",)),  # a mis-scan: measured nothing, in no figure of the lot
            rec("F", 14)]
    fpy, motors = first_pass_yield(recs)
    assert motors == 6 and fpy == pytest.approx(2 / 6)  # A and F (its first measured run) of A..F
    assert recs[1].causes() == ["max_pp_after_pct", "min_improvement_pct"]
    assert recs[3].causes() == ["error in acquire"]
    assert recs[5].causes() == ["min_r2"] and recs[6].causes() == ["wrong_serial"]
    measured = [r for r in recs if r.kind == "production"]
    # by runs: 4 runs that did not pass; B's two causes are one run, so its second adds no share
    assert pareto(measured) == [("error in acquire", 1, pytest.approx(1 / 4)), ("max_pp_after_pct", 1, pytest.approx(2 / 4)),
                                ("max_pp_before_pct", 1, pytest.approx(3 / 4)), ("min_improvement_pct", 1, pytest.approx(3 / 4)),
                                ("min_r2", 1, pytest.approx(1.0))]
