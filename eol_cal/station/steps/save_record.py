"""Step ``record``: the one record of the run (:func:`eol_cal.station.outcome.to_record`) into the
run directory's ``report.json``, then the database, or the spool when the database cannot take
it (:func:`eol_cal.records.spool.save_record`); the record journaled at the verdict leaves the
spool once the database has it. A main thread stuck in the database write (a share that hangs)
still leaves the record in the spool when the watchdog ends the process."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from eol_cal.infra.interrupts import emergency
from eol_cal.records.record import RunRecord
from eol_cal.station.context import CycleContext, now_iso
from eol_cal.station.outcome import to_record

if TYPE_CHECKING:
    from eol_cal.records.spool import SaveResult

NAME = "record"


def run(ctx: CycleContext) -> tuple[RunRecord, SaveResult]:
    ctx.ended_at = now_iso()
    assert ctx.helper is not None  # start_context made the pool
    ctx.helper.shutdown(wait=True)
    # imported after the verdict (the lot page's modules: 0.2 s at `eol-cal run`'s start; the
    # database's library), by the helper while the dyno turned (acquire_before.preload_writers)
    from eol_cal.records.spool import default_spool_dir, save_record, spool_record
    from eol_cal.station.report_files import write_record_json

    rec = to_record(ctx)
    try:
        write_record_json(rec, ctx.run_dir)
    except Exception as exc:  # noqa: BLE001 - the database still gets it
        rec = dataclasses.replace(rec, report_error=f"report.json: {type(exc).__name__}: {exc}")

    def spool_now() -> None:  # the emergency path (the watchdog's thread): straight into the spool
        spool_record(rec, ctx.cfg.db, ctx.cfg.spool_dir or default_spool_dir(), "the process was ended by a signal "
                     "while it wrote the database")

    try:
        with emergency(spool_now):
            saved = save_record(rec, ctx.cfg.db, ctx.cfg.spool_dir, ctx.cfg.db_timeout_s)
        if ctx.journal is not None and saved.where == "db":
            ctx.journal.unlink(missing_ok=True)
    finally:  # the final record is where it goes (or the journal is all there is): a flush may take it
        if ctx.journal_held is not None:
            ctx.journal_held.release()
    return rec, saved
