"""Step ``pre-flight``: the settings the cycle will flash with, then dyno ready, ECU answering and
accepting the key, serials agreeing, before anything is written to the ECU
(:mod:`eol_cal.station.preflight`); any problem stops the cycle here, a refusal."""

from __future__ import annotations

from eol_cal.station.context import CycleContext
from eol_cal.station.preflight import PreflightFailed

NAME = "pre-flight"


def run(ctx: CycleContext) -> None:
    ctx.cfg.estimator_options  # noqa: B018 - refuses options that cannot be flashed (a settings refusal)
    ctx.preflight = ctx.instruments.preflight(ctx.cfg.serial)
    if ctx.preflight.problems:
        raise PreflightFailed(ctx.preflight.problems)
