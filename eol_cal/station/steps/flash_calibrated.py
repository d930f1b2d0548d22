"""Step ``flash``: write the calibrated block into the ECU's inactive bank (read back before its
CRC unless the settings say not, ``flash.read_back``), on the session opened during the fit. The
calibration capture's file, written beside the flash (from its download on), must be on disk
before the block's CRC makes it count: a write that failed aborts the flash there (the CRC is
never written, the previous block stays active)."""

from __future__ import annotations

from eol_cal.firmware.block import pack
from eol_cal.station.context import CycleContext

NAME = "flash"


def run(ctx: CycleContext) -> None:
    assert ctx.calibrated is not None  # the table step, run before, made it
    # the calibration capture's file is written from the download on (the bus's time, not the
    # fit's nor the flash's first half's), and waited for before the CRC
    ctx.flash(pack(ctx.calibrated), "calibrated", before_commit=ctx.settle_writes, ahead=ctx.ahead,
              writes_from="download")
