"""Step ``verdict``: whatever ended the measuring steps, the run's verdict is fixed here, before the
report. The calibrated flash's session still open is left, the capture files written aside are
waited for; a failure becomes the record's error (:func:`eol_cal.station.outcome.record_failure`),
a motor left on the uncompensated block says so in its reasons; the record at the verdict goes
into the spool (durable: a station killed from then on loses nothing, the next start writes it
into the database) and only then is it shown (``on_verdict(record, spooled)``; ``spooled`` False
when the spool could not take it: the record is written at once, before the next serial). Not a step of the record's
``steps``: the executor's events name it (what a live screen shows)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path

from eol_cal.errors import EolCalError
from eol_cal.records.record import RunRecord
from eol_cal.station.context import CycleContext, now_iso
from eol_cal.station.outcome import ecu_active_of, record_failure, to_record, uncalibrated

NAME = "verdict"


def run(ctx: CycleContext, on_verdict: Callable[[RunRecord, bool], None] | None = None) -> RunRecord:
    ctx.close_flash_ahead()  # a cycle that ended before its flash: the session is left
    try:
        ctx.settle_writes()  # the cycle ended before the flash waited for them
    except EolCalError as exc:
        ctx.failure = ctx.failure or exc
    if ctx.failure is not None:
        record_failure(ctx, ctx.failure)
    ctx.ecu_active = ecu_active_of(ctx, ctx.failure)
    if ctx.failure is not None and ctx.ecu_active.block.startswith("uncompensated"):
        # the calibration state is part of the outcome: said in the record, not only on screen
        ctx.reasons = [*ctx.reasons, uncalibrated(ctx.ecu_active, ctx.steps[-1].step if ctx.steps else "start",
                                                  ctx.cfg.dyno)]
    ctx.ended_at = now_iso()
    rec = to_record(ctx)
    ctx.journal = journal(ctx, rec)
    if on_verdict is not None:
        with contextlib.suppress(Exception):  # a display that fails must not cost the record
            on_verdict(rec, ctx.journal is not None)  # the screen says where the record is only if it is
    return rec


def journal(ctx: CycleContext, rec: RunRecord) -> Path | None:
    """The record at the verdict, into the spool before anyone sees the verdict; None when the
    spool cannot be written (the database is tried all the same after the report)."""
    # SQLAlchemy: loaded on the helper meanwhile
    from eol_cal.records.spool import default_spool_dir, hold_in_flight, spool_record

    spool_dir = ctx.cfg.spool_dir or default_spool_dir()
    try:
        # held until the final record is written (save_record): a flush from another process
        # meanwhile would insert this version and the final one would be refused as a duplicate
        ctx.journal_held = hold_in_flight(spool_dir, rec.run_id)
        return spool_record(rec, ctx.cfg.db, spool_dir,
                            "written at the verdict, before the report; the run's process ended before "
                            "it wrote the record into the database")
    except OSError:
        if ctx.journal_held is not None:
            ctx.journal_held.release()
            ctx.journal_held = None
        return None
