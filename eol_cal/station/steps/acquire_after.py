"""Step ``acquire compensated``: the capture with the compensation the ECU now runs (the operating
point's segment, or the whole profile with ``verify = "full"``); the calibration capture's figures
at the operating point are worked out meanwhile on the helper thread, and each window's as it arrives."""

from __future__ import annotations

from eol_cal.analysis.point_metrics import nearest_segment, point_ripple, verify_segments
from eol_cal.station.context import CycleContext
from eol_cal.station.early import EarlyWindows

NAME = "acquire compensated"


def run(ctx: CycleContext) -> None:
    # the steps run in order and stop at the first that fails: the fit gave a result, start_context made the pool
    assert ctx.result is not None and ctx.fit_extra is not None and ctx.helper is not None
    op = ctx.result.operating_point
    segs = ctx.segments if ctx.cfg.verify == "full" else verify_segments(ctx.segments, op.speed_rpm, op.i_qo_a)
    mi = ctx.fit_extra[0]
    k = nearest_segment(mi.captures, op.speed_rpm, op.i_qo_a)
    ctx.pr_before = ctx.helper.submit(point_ripple, mi.captures[k], mi.angles[k])
    ctx.verify = EarlyWindows(ctx.cfg.motor.poles, ctx.cfg.motor.N_enc, pool=ctx.helper, measure=point_ripple)
    ctx.after = ctx.acquire("after", segs, on_window=ctx.verify.on_window)
