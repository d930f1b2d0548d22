"""Step ``metrics``: the ripple before and after at the operating point (the record's metrics),
judged against the ripple's limits (stage ``ripple``); a master motor's run also against its
references (:func:`eol_cal.msa.gate.judge_master`)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from eol_cal.analysis.point_metrics import PointRipple, nearest_segment
from eol_cal.capture.windows import split_windows
from eol_cal.records.limits import LimitCheck, Measured, VariantLimits, failed, judge
from eol_cal.records.record import RippleMetrics
from eol_cal.station.context import CycleContext, StepVerdict, point_figures

if TYPE_CHECKING:
    from eol_cal.analysis.motor_result import MotorResult

NAME = "metrics"
RIPPLE_DEFINITION = ("filtered p-p % (docs/metrics.md), median over the steady windows of the operating point's "
                     "segment")


def run(ctx: CycleContext) -> StepVerdict:
    # the steps before this one gave them (the cycle stops at the first step that fails)
    assert ctx.result is not None and ctx.measured is not None
    assert ctx.pr_before is not None and ctx.verify is not None and ctx.after is not None
    op = ctx.result.operating_point
    before = ctx.pr_before.result()
    pieces = split_windows(ctx.after)
    after = ctx.verify.measured(pieces[nearest_segment(pieces, op.speed_rpm, op.i_qo_a)])
    ctx.point_ripples = (before, after)
    ctx.metrics, ctx.measured, ctx.judged["ripple"] = judge_ripple(ctx.result, before, after, ctx.measured,
                                                                   ctx.cfg.limits)
    reasons = failed(ctx.judged["ripple"])
    if ctx.cfg.kind == "master" and ctx.cfg.master is not None:  # the master check: within its references
        from eol_cal.msa.gate import judge_master  # the records database's library: loaded by a master run only

        e = ctx.result.estimates
        assert e is not None  # the fit step passed: its result is usable (it has estimates)
        checks = judge_master({"k6": e.k6.value, "phase_k6": e.phase_k6.value, "c6": e.c6.value,
                               "pp_before_pct": before.pp_pct, "pp_after_pct": after.pp_pct}, ctx.cfg.master)
        reasons += [c.reason for c in checks if c.reason is not None]
        if ctx.gate_info is not None:
            ctx.gate_info = dataclasses.replace(ctx.gate_info, checks=tuple(checks))
    return StepVerdict("fail" if reasons else "pass", tuple(reasons))


def judge_ripple(result: MotorResult, before: PointRipple, after: PointRipple, measured: Measured,
                 limits: VariantLimits) -> tuple[RippleMetrics, Measured, list[LimitCheck]]:
    """The record's ripple metrics at the fit's operating point, the measured values with the
    ripple (the p-p figures in %, the order-1 amplitude left in N*m) and the ripple's limits
    judged: the station's cycle and a what-if lot (:mod:`eol_cal.station.whatif`) judge alike."""
    op = result.operating_point
    metrics = RippleMetrics(float(op.speed_rpm), float(op.i_qo_a), point_figures(before), point_figures(after),
                            RIPPLE_DEFINITION)
    measured = measured.with_ripple(before.pp_pct, after.pp_pct, after.pp_no_mech1_pct, after.mech1_nm)
    return metrics, measured, judge(measured, limits, "ripple")
