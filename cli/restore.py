"""``eol-cal ecu restore``: an earlier calibration made active again (docs/station.md, "Restoring an
earlier calibration"): from the run records (``--calibration previous``, ``--run``), a bank or a
file; recorded as a run of kind ``restore`` with ``--db``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from cli.common import RECORDS_DB, err_console, handle_errors, print_json
from cli.ecu import bank_choice, bus_options, open_cli_bus, key_from_options, ecu_group, key_algo_option
from cli.paths import io_paths
from eol_cal.errors import InputError


@click.command("restore")
@click.option("--bank", default=None, metavar="0|1|previous",
              help="Restore the block in this bank; previous: the bank that is not active (after a station run: "
                   "its uncompensated prepare block, refused without --force).")
@click.option("--from", "from_file", type=click.Path(dir_okay=False), default=None,
              help="Restore this block file instead (a run directory's block.bin, raw or Intel HEX).")
@click.option("--calibration", type=click.Choice(["previous"]), default=None,
              help="previous: the calibrated block of --serial's latest passing run (in --db) that is not the one "
                   "the ECU runs now: the calibration before the last run.")
@click.option("--run", "run_id", default=None, metavar="RUN_ID", help="The calibrated block run RUN_ID archived (in --db).")
@click.option("--serial", default=None, help="The motor (with --calibration; checked against the ECU's F18C).")
@click.option("--db", default=None, type=RECORDS_DB,
              help="Records database: where --calibration/--run look, and where the restore is recorded (kind restore).")
@click.option("--report-dir", default="reports", show_default=True, type=click.Path(file_okay=False, path_type=Path),
              help="With --db: the restore's run directory (the block as flashed, report.json) goes here.")
@click.option("--spool-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Where the record waits when the database cannot be written (as for run).")
@click.option("--force", is_flag=True, help="Restore a block without compensation, or a run's block that did not pass.")
@bus_options
@click.option("--key-file", type=click.Path(dir_okay=False), help="Security secret, 16 bytes as hex.")
@key_algo_option
@click.option("--save", "save_file", type=click.Path(dir_okay=False), default=None,
              help="Write the block read from the bank here before flashing (written atomically) "
                   "[default: ecu-bankN-TIME.bin in the current directory].")
@click.option("--motor", "motor_file", type=click.Path(dir_okay=False),
              help="Motor TOML overriding the paper preset: its current rating bounds the block.")
@click.option("--json", "as_json", is_flag=True, help="Print the flash report (and the record) as JSON.")
@handle_errors
@io_paths(inputs=("from_file", "key_file", "can_config", "motor_file"), outputs=("save_file",),
          output_dirs=("report_dir", "spool_dir"), databases=("db",))
def restore_cmd(bank: str | None, from_file: str | None, calibration: str | None, run_id: str | None,
                serial: str | None, db: Any, report_dir: Path, spool_dir: Path | None, force: bool,
                interface: str | None, channel: str | None, bitrate: int | None, can_config: str | None,
                key_file: str | None, key_algo: str | None, save_file: str | None, motor_file: str | None,
                as_json: bool) -> None:
    """Make an earlier calibration active again: flash it anew with a higher sequence.

    The block comes from the run records (--calibration previous --serial S, or --run RUN_ID,
    with --db: the calibrated block that run archived, byte for byte as flashed, its SHA-256
    checked), from a bank of the ECU (--bank 0|1|previous) or from a file (--from). It is
    checked (valid, CRC, physical sanity) and written like `eol-cal flash` writes: into the
    inactive bank, read back, checked, confirmed after the reset. A block that holds no
    compensation (a station run's prepare block: after a passing run, the previous bank holds
    it) is refused unless --force. Restoring the previous bank rewrites that very bank: the block
    read is kept in a file first (--save, or ecu-bankN-TIME.bin here). With --db the restore is
    recorded as a run of kind restore. Exit 0 restored (or already active), 1 verification
    failed, 2 refused or error.
    """
    from eol_cal.domain.motor_params import load_motor
    from eol_cal.station.restore import prepare_note, uncompensated

    chosen = [x for x in (bank, from_file, calibration, run_id) if x is not None]
    if len(chosen) != 1:
        raise InputError(None, "bank", "give one of --bank 0|1|previous, --from FILE, --calibration previous or --run RUN_ID")
    if (calibration or run_id) and db is None:
        raise InputError(None, "db", "--calibration and --run find the block in the run records: give --db")
    motor = load_motor("paper", motor_file)
    seed_to_key = key_from_options(key_file, key_algo)
    records = _serial_records(db, serial if not run_id else None) if db is not None else []
    restored_from = None
    if calibration or run_id:
        found = _from_records(records, serial, run_id, force, (interface, channel, bitrate, can_config))
        data, source, restored_from = found.data, found.source, found.restored_from()
        serial = serial or found.record.serial
    else:
        got = _from_bank_or_file(bank, from_file, save_file, motor, (interface, channel, bitrate, can_config))
        if got is None:
            return
        data, source = got
        if uncompensated(data) and not force:
            raise InputError(source, "block", prepare_note(data, source, records))
        restored_from = _restored_from(source, data)
    report, rec, saved = _restore(data, source, serial, db, report_dir, spool_dir, seed_to_key, motor, restored_from,
                                  (interface, channel, bitrate, can_config), as_json)
    if as_json:
        print_json({"schema": "eol-cal/ecu-restore/1", **report.to_dict(), "restored_from": source,
                    "record": None if rec is None else rec.to_json(),
                    "saved": None if saved is None else {"where": saved.where, "path": saved.path, "why": saved.why}})
        return
    prev = f"bank {report.previous.bank} seq {report.previous.sequence}" if report.previous.has_bank else "none"
    click.echo(f"restored {source} into bank {report.bank}: active now, seq {report.sequence} crc {report.crc32:08x} "
               f"({'verified' if report.verified else 'NOT read back'}); active before: {prev}")
    if rec is not None:
        where = f"database {saved.path}" if saved.where == "db" else f"SPOOL {saved.path} ({saved.why})"
        click.echo(f"record {rec.run_id} (kind restore) -> {where}; archive {rec.blocks[-1].path}")


def _serial_records(db: Any, serial: str | None) -> list:
    """The records of ``serial`` (every serial: None); none yet in a database file not created yet."""
    from eol_cal.records.connect import is_url
    from eol_cal.records.query import query_records

    if not is_url(db) and not Path(db).exists():
        return []
    return query_records(db, serial=serial)


def _from_records(records: list, serial: str | None, run_id: str | None, force: bool, bus_args: tuple):
    """The calibration the records hold (not the one the ECU runs now), checked against the ECU's serial."""
    from eol_cal.ecu.client import ecu_state
    from eol_cal.station.restore import find_calibration

    bus = open_cli_bus(*bus_args)
    try:
        state = ecu_state(bus)
    finally:
        bus.shutdown()
    found = find_calibration(records, serial, run_id=run_id, active=state, force=force)
    if state.serial is not None and state.serial != found.record.serial and not force:
        raise InputError(None, "serial", f"the ECU reports serial {state.serial} (F18C), the calibration is of "
                                         f"{found.record.serial}: another motor's ECU (--force to flash it anyway)")
    return found


def _from_bank_or_file(bank: str | None, from_file: str | None, save_file: str | None, motor: Any,
                       bus_args: tuple) -> tuple[bytes, str] | None:
    """The block of ``--bank`` (kept in a file first) or ``--from``; None: the bank is active already."""
    import time

    from eol_cal.infra.atomic import atomic_write
    from eol_cal.ecu.reflash import check_restorable, read_bank_block
    from eol_cal.firmware.block import read_block_file

    if from_file is not None:
        return read_block_file(from_file), from_file
    bus = open_cli_bus(*bus_args)
    try:
        got = read_bank_block(bus, bank_choice(bank))
    finally:
        bus.shutdown()  # a UDS session closes its link with it: the flash opens its own
    if got.is_active:
        click.echo(f"bank {got.bank} is the active block already (sequence {got.active.sequence}): nothing to do")
        return None
    check_restorable(got.data, got.source, motor)  # a bank not worth restoring is refused before any copy
    if save_file is None:  # the flash erases this very bank first: never without a copy
        save_file = time.strftime(f"ecu-bank{got.bank}-%Y%m%dT%H%M%SZ.bin", time.gmtime())
    try:
        atomic_write(save_file, got.data)
    except OSError as exc:
        raise InputError(save_file, None, f"cannot write: {exc}; nothing was flashed") from exc
    click.echo(f"bank {got.bank}'s block kept in {save_file} (eol-cal ecu restore --from {save_file})", err=True)
    return got.data, got.source


def _restored_from(source: str, data: bytes):
    import hashlib

    from eol_cal.firmware import block as B
    from eol_cal.records.record import RestoredFrom

    blk = B.unpack(data, source)
    return RestoredFrom(None, source, hashlib.sha256(data).hexdigest(), blk.sequence,
                        f"{B.check(data).crc_stored or 0:08x}")


def _restore(data: bytes, source: str, serial: str | None, db: Any, report_dir: Path, spool_dir: Path | None,
             seed_to_key: Any, motor: Any, restored_from: Any, bus_args: tuple, as_json: bool):
    """The flash: recorded (a run of kind restore) when a database is given, else as before."""
    from eol_cal.ecu.client import ClientTiming
    from eol_cal.ecu.reflash import restore_block
    from eol_cal.firmware.block import unpack
    from eol_cal.records.record import StationInfo
    from eol_cal.station.restore import restore_run

    progress = None if as_json else (lambda s: err_console.print(f"  {s}", style="dim"))
    if db is None:
        bus = open_cli_bus(*bus_args)
        try:
            return restore_block(bus, data, source, seed_to_key=seed_to_key, motor=motor, progress=progress), None, None
        finally:
            bus.shutdown()
    report, rec, saved, failure = restore_run(
        lambda: open_cli_bus(*bus_args), data, serial=serial or unpack(data, source).serial, report_dir=report_dir,
        seed_to_key=seed_to_key, timing=ClientTiming(), motor=motor, source=source, restored_from=restored_from,
        station=StationInfo(extra={"command": "ecu restore", "can": {"interface": bus_args[0], "channel": bus_args[1]}}),
        db=db, spool_dir=spool_dir, progress=progress)
    if failure is not None:
        raise failure
    return report, rec, saved


ecu_group.add_command(restore_cmd)
COMMANDS: list = []  # a subcommand of `eol-cal ecu` (cli/ecu.py)
