"""Step ``table``: the calibrated block from the fit (lead automatic)."""

from __future__ import annotations

from eol_cal.analysis.fit.table import block_from_result, created_unix
from eol_cal.station.context import CycleContext

NAME = "table"


def run(ctx: CycleContext) -> None:
    assert ctx.result is not None and ctx.fit_doc is not None  # the fit step, run before, passed
    ctx.calibrated = block_from_result(ctx.result, ctx.cfg.motor, calibrated_at=created_unix(ctx.fit_doc),
                                       source=str(ctx.run_dir / "fit.json"), options=ctx.cfg.estimator_options)
