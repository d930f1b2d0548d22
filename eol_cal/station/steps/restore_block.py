"""Step ``restore`` (``eol-cal ecu restore``, not a step of the calibration cycle): an earlier block
flashed again as a new sequence (the ECU boots the highest), archived as flashed in the run's
directory. A flash that fails after the block's CRC went out leaves its archived block in the
context (the record says the ECU boots it)."""

from __future__ import annotations

from eol_cal.station.archive import flash_archived, keep_flashed
from eol_cal.station.context import RestoreContext

NAME = "restore"
#: the archive file of a restore run's directory
RESTORE_ARCHIVE = "block_restore.bin"


def run(ctx: RestoreContext) -> None:
    ctx.report = keep_flashed(ctx.blocks, lambda: flash_archived(
        ctx.open_bus, ctx.data, role="restore", path=ctx.run_dir / RESTORE_ARCHIVE, seed_to_key=ctx.seed_to_key,
        timing=ctx.timing, motor=ctx.motor, source=ctx.source, progress=ctx.progress))
