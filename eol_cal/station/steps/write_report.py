"""Step ``report``: the per-motor HTML report with the fit's plots, drawn now (after the verdict
is shown). A report that fails costs the run its ``pass`` (verdict ``error``, ``report_error``),
never its record."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from eol_cal.station.context import CycleContext
from eol_cal.station.outcome import to_record

NAME = "report"


def run(ctx: CycleContext) -> Path:
    from eol_cal.station.report_files import fit_plots, write_report  # matplotlib: after the verdict

    if not ctx.cfg.report_plots:  # the page without its plots (StationConfig.report_plots)
        return write_report(to_record(ctx), ctx.run_dir, figures=[])
    figures = fit_plots(ctx.run_dir, ctx.fit_extra) if ctx.fit_extra is not None else []
    return write_report(to_record(ctx), ctx.run_dir, figures=figures, fit_extra=ctx.fit_extra,
                        point_ripple=ctx.point_ripples)


def failed(ctx: CycleContext, exc: Exception) -> None:
    """The report's failure, into the step's entry, the record's ``report_error`` and the verdict."""
    ctx.steps[-1] = dataclasses.replace(ctx.steps[-1], error=f"{type(exc).__name__}: {exc}")
    ctx.report_error = f"{type(exc).__name__}: {exc}"
    if ctx.verdict != "error":
        ctx.verdict = "error"
        ctx.reasons = ctx.reasons + [f"report: {exc}"]
