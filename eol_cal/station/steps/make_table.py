"""Step ``table``: the calibrated block from the fit (lead automatic)."""

from __future__ import annotations

from eol_cal.analysis.fit.table import block_from_result, unix_seconds
from eol_cal.station.context import CycleContext

NAME = "table"


def run(ctx: CycleContext) -> None:
    assert ctx.result is not None and ctx.fitted is not None  # the fit step, run before, passed
    fit_file = str(ctx.run_dir / "fit.json")
    ctx.calibrated = block_from_result(ctx.result, ctx.cfg.motor, calibrated_at=unix_seconds(ctx.fitted.created, fit_file),
                                       source=fit_file, options=ctx.cfg.estimator_options)
