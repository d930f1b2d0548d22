"""Restoring what the user means: an earlier calibration found through the run records, flashed
again, and recorded as a run of kind ``restore``.

A station run flashes two blocks (:mod:`eol_cal.station.cycle`): the uncompensated *prepare*
block, then the calibrated one. After a passing run the ECU's other bank therefore holds the
prepare block, not the motor's earlier calibration: restoring "the previous bank" would flash
a block without compensation. The earlier calibration lives in the records: the calibrated block
each passing run archived (:mod:`eol_cal.station.archive`, byte for byte as flashed, its SHA-256
in the record). :func:`find_calibration` picks it (``--calibration previous``: the serial's
latest passing production run whose calibrated block is not the one the ECU runs now; ``--run``:
that run's), :func:`restore_run` flashes it as a new sequence (the ECU boots the highest) and
records the run.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence

from eol_cal.errors import InputError
from eol_cal.records.record import MEASURED_KIND, FlashedBlock, RestoredFrom, RunRecord, StationInfo

if TYPE_CHECKING:
    from eol_cal.capture.ecu_state import EcuState
    from eol_cal.ecu.sequence import FlashReport
    from eol_cal.domain.motor_params import MotorParams
    from eol_cal.records.spool import SaveResult
    from eol_cal.station.executor import Observer

@dataclass(frozen=True)
class Calibration:
    """A calibration the records hold: the run that flashed it, its archived block and bytes."""

    record: RunRecord
    block: FlashedBlock
    data: bytes

    @property
    def source(self) -> str:
        return f"the calibrated block of run {self.record.run_id} ({self.record.started_at[:19]}Z, {self.block.path})"

    def restored_from(self) -> RestoredFrom:
        b = self.block
        return RestoredFrom(self.record.run_id, str(b.path), b.sha256, b.sequence, b.crc32)


def read_archive(block: FlashedBlock, run_id: str) -> bytes:
    """The archived block's bytes, checked against the SHA-256 the record holds (when it holds one)."""
    import hashlib

    if not block.path:
        raise InputError(None, f"run {run_id} blocks", f"the {block.role} block has no archive file")
    from eol_cal.firmware.block_layout import BANK_BYTES
    from eol_cal.infra.inputs import read_bytes

    try:  # a path from a record: no FIFO, no device, no gigabytes
        data = read_bytes(block.path, None, max_bytes=4 * BANK_BYTES)
    except InputError as exc:
        raise InputError(block.path, None, f"the archive of run {run_id} cannot be read: {exc.reason}") from None
    if block.sha256 is not None and hashlib.sha256(data).hexdigest() != block.sha256:
        raise InputError(block.path, "sha256", f"the file is not the block run {run_id} flashed (its SHA-256 "
                                               f"differs from the record's {block.sha256[:16]}...)")
    return data


def _same_block(b: FlashedBlock, state: EcuState | None) -> bool:
    return state is not None and state.has_block and (b.sequence, b.crc32) == (state.sequence, state.crc32)


def find_calibration(records: Sequence[RunRecord], serial: str | None, *, run_id: str | None = None,
                     active: EcuState | None = None, force: bool = False) -> Calibration:
    """The calibration to restore.

    Parameters
    ----------
    records : sequence of RunRecord
        The records database's records of the serial (any kind; only production runs count).
    serial : str or None
        The motor (with ``run_id`` it must be that run's, when given).
    run_id : str or None
        That run's calibrated block (a run that did not pass is refused unless ``force``);
        None: the serial's latest passing run whose calibrated block is not ``active``.
    active : EcuState or None
        What the ECU runs now.

    Raises
    ------
    InputError
        No such run, no passing run with an archived calibration, a run of another serial.
    """
    if run_id is not None:
        rec = next((r for r in records if r.run_id == run_id), None)
        if rec is None:
            raise InputError(None, "run", f"no run {run_id} in the records")
        if serial is not None and rec.serial != serial:
            raise InputError(None, "serial", f"run {run_id} is of serial {rec.serial}, not {serial}")
        block = rec.block("calibrated")
        if block is None:
            raise InputError(None, "run", f"run {run_id} ({rec.kind}, {rec.verdict}) flashed no calibrated block")
        if rec.verdict != "pass" and not force:
            raise InputError(None, "run", f"run {run_id} ended {rec.verdict} ({'; '.join(rec.reasons)}): its "
                                          "calibration was not accepted; restore it only on purpose (--force)")
        return Calibration(rec, block, read_archive(block, rec.run_id))
    if serial is None:
        raise InputError(None, "serial", "--calibration previous needs the motor's serial")
    passing = sorted((r for r in records if r.serial == serial and r.kind == MEASURED_KIND and r.verdict == "pass"
                      and r.block("calibrated") is not None), key=lambda r: (r.started_at, r.run_id))
    candidates = [r for r in passing if not _same_block(_calibrated(r), active)]
    if not candidates:
        why = "no passing run with a calibrated block" if not passing else \
            f"only the calibration the ECU runs now (run {passing[-1].run_id})"
        raise InputError(None, "calibration", f"serial {serial}: the records hold {why}: nothing earlier to restore")
    rec = candidates[-1]
    block = _calibrated(rec)
    return Calibration(rec, block, read_archive(block, rec.run_id))


def _calibrated(rec: RunRecord) -> FlashedBlock:
    """The calibrated block of a record that holds one (as every record ``passing`` keeps)."""
    block = rec.block("calibrated")
    assert block is not None
    return block


def uncompensated(data: bytes) -> bool:
    """The block compensates nothing: its flags leave the compensation off, or its tables are zero."""
    import numpy as np

    from eol_cal.firmware import block as B

    blk = B.unpack(data, "<block>")
    zero = not np.any(np.asarray(blk.table_const)) and not np.any(np.asarray(blk.table_per_amp))
    return not (blk.flags & B.FLAG_COMP_ENABLE) or zero


def prepare_note(data: bytes, source: str, records: Sequence[RunRecord] = ()) -> str:
    """Why restoring ``data`` is refused: it holds no compensation; the run that flashed it as its
    prepare block when the records know it; the way to the earlier calibration."""
    from eol_cal.firmware import block as B

    blk = B.unpack(data, source)
    crc = f"{B.check(data).crc_stored or 0:08x}"
    by = next((r for r in records for b in r.blocks if b.role == "prepare" and (b.sequence, b.crc32) ==
               (blk.sequence, crc)), None)
    what = (f"the prepare block of run {by.run_id} ({by.started_at[:19]}Z)" if by is not None
            else "the uncompensated block a station run flashes before its calibration capture (its prepare block)")
    return (f"{source} holds no compensation (flags {B.flag_names(blk.flags)}, sequence {blk.sequence}, CRC {crc}): "
            f"{what}; restoring it leaves motor {blk.serial} uncompensated. The calibration before the last run "
            f"is in the run records: eol-cal ecu restore --serial {blk.serial} --calibration previous --db DB "
            "(or --force to restore this block all the same)")


def restore_run(open_bus: Callable[[], Any], data: bytes, *, serial: str, report_dir: Path,
                seed_to_key: Callable[[bytes], bytes], timing: Any, motor: MotorParams, source: str,
                restored_from: RestoredFrom, station: StationInfo, db: str | Path | None = None,
                spool_dir: Path | None = None, db_timeout_s: float = 5.0,
                progress: Callable[[str], None] | None = None, observers: Sequence[Observer] = ()
                ) -> tuple[FlashReport | None, RunRecord, SaveResult | None, BaseException | None]:
    """Flash ``data`` again (a new sequence: the ECU boots it), archive it as flashed in a new run
    directory under ``report_dir``, and record the run (kind ``restore``) in ``db`` (or its spool;
    None: the record is only the run directory's ``report.json``).

    One step, ``restore`` (:mod:`eol_cal.station.steps.restore_block`), through the station's executor
    (``observers`` get its start and end); the record is built by
    :func:`eol_cal.station.outcome.restore_record`. Returns the flash report (None when the flash
    failed), the record, where it was saved, and the exception that ended the flash (None:
    restored); the caller re-raises it.
    """
    # the station's context and executor load python-can: at the restore, not at the command's start
    from eol_cal.station.context import RestoreContext
    from eol_cal.station.executor import Executor
    from eol_cal.station.outcome import restore_record
    from eol_cal.station.report_files import write_record_json
    from eol_cal.station.run import new_run_dir
    from eol_cal.station.steps import restore_block

    started = dt.datetime.now(dt.UTC)
    run_id = uuid.uuid4().hex
    run_dir = new_run_dir(report_dir, serial, started, run_id)
    ctx = RestoreContext(serial, run_id, started, run_dir, data, source, open_bus, seed_to_key, timing, motor,
                         restored_from, station, progress)
    try:
        Executor(observers).timed(ctx, restore_block.NAME, restore_block.run)
    except BaseException as exc:  # noqa: BLE001 - recorded, then raised again by the caller
        ctx.failure = exc
        ctx.steps[-1] = dataclasses.replace(ctx.steps[-1], error=str(exc))
    rec = restore_record(ctx)
    try:
        write_record_json(rec, run_dir)
    except OSError as exc:
        rec = dataclasses.replace(rec, report_error=f"report.json: {type(exc).__name__}: {exc}")
    saved = None
    if db is not None:
        from eol_cal.records.spool import save_record

        saved = save_record(rec, db, spool_dir, db_timeout_s)
    return ctx.report, rec, saved, ctx.failure
