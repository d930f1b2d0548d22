"""Step ``fit``: fit the calibration capture; a fit that is not usable or out of the fit's limits
fails the motor here (judged once, :func:`eol_cal.records.limits.judge`, stage ``fit``).

What is left when the capture is in: the hall table, the firmware frame (on threads) and the
joint solve (its solver traced during the capture). The calibrated flash's first half runs
meanwhile, opened by the acquire step (or here: :meth:`~eol_cal.station.context.CycleContext.open_flash_ahead`)."""

from __future__ import annotations

from eol_cal import __version__
from eol_cal.analysis.result import write_result
from eol_cal.records.limits import Measured, failed, judge
from eol_cal.station.context import CycleContext, StepVerdict
from eol_cal.station.run import check_motor, fit_motor

NAME = "fit"


def run(ctx: CycleContext) -> StepVerdict | None:
    # never two fits at once: JAX tracing, the compilation cache and the fit's solver cache
    # are shared by the threads, and a cold start compiles the same solver in both
    assert ctx.before is not None  # the acquire step, run before, captured it
    check_motor(ctx.before, ctx.cfg.motor)
    ctx.open_flash_ahead()
    assert ctx.prewarm is not None  # the acquire step, run before, started it
    ctx.prewarm.result()
    fitted, res, extra = fit_motor(ctx.before, ctx.cfg.limits, __version__, ctx.cfg.motor, ctx.cfg.mechanics,
                                   ctx.cfg.cache_dir, ctx.cfg.estimator_options, prepared=ctx.early)
    write_result(fitted.to_json(), ctx.run_dir / "fit.json")
    ctx.fitted, ctx.result, ctx.fit_extra = fitted, res, extra
    if not res.usable:
        return StepVerdict("fail", tuple(f"fit {res.status}: {r}" for r in res.reasons) or (f"fit {res.status}",))
    ctx.measured = Measured.of_fit(res)
    ctx.judged["fit"] = judge(ctx.measured, ctx.cfg.limits, "fit")
    reasons = failed(ctx.judged["fit"])
    return StepVerdict("fail", tuple(reasons)) if reasons else None
