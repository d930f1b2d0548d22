"""Step ``prepare ECU``: flash the uncompensated block, so the calibration capture sees the field
estimator alone, with the same estimator options as the calibrated block will carry. From here
the run is a measured attempt (kind ``production``, not ``refusal``)."""

from __future__ import annotations

from eol_cal.analysis.fit.table import uncompensated_block
from eol_cal.firmware.block import pack
from eol_cal.station.context import CycleContext

NAME = "prepare ECU"


def run(ctx: CycleContext) -> None:
    ctx.touched = True
    ctx.uncompensated = uncompensated_block(ctx.cfg.serial, ctx.cfg.motor, options=ctx.cfg.estimator_options)
    ctx.flash(pack(ctx.uncompensated), "prepare")
