"""The interval limits (issue 39, item 3): the fit's status (``ci_too_wide``) and the station's
limits table (``max_ci_*`` of ``LIMITS``) judge the same quantities with the same comparison
(:mod:`eol_cal.analysis.intervals`), so at any limit values, on the boundary too, they agree."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.analysis.fit import Estimate, FitSpec, MotorFit
from eol_cal.analysis.intervals import CiLimits, ci_phasor, ci_rel
from eol_cal.analysis.result import STATUS_CI_TOO_WIDE, STATUS_OK, judge, motor_result
from eol_cal.records.limits import LIMITS, Measured, VariantLimits
from eol_cal.records.limits import judge as judge_stage

SPEC = FitSpec(harmonics=(6,))
#: a limits file's other fit-stage rows, set wide: only the interval rows can fail
WIDE = dict(max_k6=1.0, max_pp_before_pct=1000.0, max_pp_after_pct=1000.0, min_improvement_pct=-1000.0, min_r2=-1.0,
            max_rms_nm=100.0, max_hall_deviation_deg=180.0)


def _fit(k: float, ci_k: float, phase_ci_k: float, c: float, ci_c: float, phase_ci_c: float) -> MotorFit:
    return MotorFit(harmonics={6: {"k": Estimate(k, ci_k, 0.3, phase_ci_k), "c": Estimate(c, ci_c, 1.1, phase_ci_c)}},
                    delay_s=1e-4, delay_ci95=1e-6, t_avg=np.zeros(2), rms=1e-3, r2=0.9, solver_result="successful",
                    steps=4, n_samples=20000)


def _interval_rows_fail(fit: MotorFit, limits: CiLimits) -> bool:
    """Whether ``LIMITS``' interval rows fail a motor at ``limits``' values (judged as the station does)."""
    segments = [{"i_qo_a": 20.0, "speed_rpm": 120.0}, {"i_qo_a": 65.0, "speed_rpm": 240.0}]
    res = motor_result("M-1", fit, SPEC, CiLimits(math.inf, math.inf, math.inf), kt=0.05, kt_source="test", poles=6,
                       encoder_ppr=64, sources=[], segments=segments, metrics={}, solver_mode="loop")
    lim = VariantLimits.of("v", **WIDE, max_ci_k6_rel=limits.k6_rel, max_ci_phase_k6_deg=limits.phase_k6_deg,
                           max_ci_c6_nm=limits.c6_nm)
    assert lim.ci_limits() == limits  # the station hands the fit these very values
    checks = judge_stage(Measured.of_fit(res), lim, "fit")
    interval_keys = {row.key for row in LIMITS if row.ci in ("k6_rel", "phase_k6_deg", "c6_nm")}
    return any(c.passed is False for c in checks if c.key in interval_keys)


@pytest.mark.parametrize("seed", range(6))
def test_the_fit_and_the_limits_table_judge_the_intervals_alike(seed):
    rng = np.random.default_rng(seed)
    for _ in range(40):
        k, c = rng.uniform(1e-4, 1e-3), rng.uniform(1e-4, 5e-3)
        fit = _fit(k, k * rng.uniform(0.01, 0.1), rng.uniform(0.01, 0.1), c, c * rng.uniform(0.01, 0.5),
                   rng.uniform(0.01, 0.5))
        six = fit.harmonics[6]
        # each limit at the interval itself (the boundary: met), just below it (not met) and above
        widths = (ci_rel(six["k"].ci95, six["k"].value), math.degrees(six["k"].phase_ci95),
                  ci_phasor(six["c"].ci95, six["c"].value, six["c"].phase_ci95))
        for which in range(3):
            for factor in (1.0, 1 - 1e-9, 1 + 1e-9):
                values = [w * 2 for w in widths]
                values[which] = widths[which] * factor
                limits = CiLimits(*values)
                status, _ = judge(fit, SPEC, limits)
                assert status in (STATUS_OK, STATUS_CI_TOO_WIDE)
                assert (status == STATUS_CI_TOO_WIDE) == _interval_rows_fail(fit, limits), (which, factor, widths)
                assert (status == STATUS_OK) == (factor >= 1.0)
