"""``eol-cal flash``, ``eol-cal ecu info|read-block`` and ``eol-cal ecu-sim``.

CAN, ISO-TP and UDS imports stay inside the commands so ``eol-cal --help`` stays fast.
"""

from __future__ import annotations

import functools
from typing import Any
from collections.abc import Callable

import click

from cli.common import err_console, exchange_log_options, handle_errors, print_json
from cli.paths import io_paths
from eol_cal.errors import InputError


def bus_options(func: Callable) -> Callable:
    """--interface/--channel/--bitrate/--can-config, as python-can understands them."""

    @click.option("--can-config", type=click.Path(dir_okay=False),
                  help="python-can configuration file ([default] section); options given here win.")
    @click.option("--bitrate", type=int, default=None, help="bit/s (the contract's bus runs 500000).")
    @click.option("--channel", "-c", default=None,
                  help="python-can channel: can0, PCAN_USBBUS1, ws://127.0.0.1:54701/ for remote...")
    @click.option("--interface", "-i", default=None,
                  help="python-can interface: socketcan, pcan, vector, kvaser, virtual, remote...")
    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        return func(*args, **kwargs)

    return wrapper


def open_cli_bus(interface: str | None, channel: str | None, bitrate: int | None, can_config: str | None) -> Any:
    from eol_cal.ecu.transport import open_bus
    from eol_cal.infra.exchange_log import quiet

    # can-isotp and udsoncan log every lost frame and timeout; the error we raise says it once
    # (--verbose/--log-file open these loggers again).
    quiet(("isotp", "UdsClient", "Connection", "can"))

    return open_bus(interface, channel, bitrate, can_config)


def key_from_options(key_file: str | None, key_algo: str | None) -> Any:
    from eol_cal.ecu.keyalgo import seed_to_key_from

    return seed_to_key_from(key_file, key_algo)


def key_algo_option(func: Callable) -> Callable:
    """``--key-algo NAME|MODULE:FUNC``: the OEM's seed-to-key algorithm (:mod:`eol_cal.ecu.keyalgo`)."""
    return click.option(
        "--key-algo", metavar="NAME|MODULE:FUNC",
        help="The OEM's seed-to-key algorithm: an entry point of group eol_cal.seed_to_key, or MODULE:FUNC; "
             "called as FUNC(seed: bytes, secret: bytes|None) -> key bytes (secret: the --key-file's).")(func)


@click.command("flash")
@click.argument("block_file", metavar="BLOCK", type=click.Path(dir_okay=False))
@bus_options
@click.option("--key-file", type=click.Path(dir_okay=False), help="Security secret, 16 bytes as hex.")
@key_algo_option
@click.option("--verify/--no-verify", default=True, show_default=True, help="Read the block back and compare.")
@click.option("--dry-run", is_flag=True, help="Identify and unlock the ECU, check the block against it, write nothing.")
@click.option("--force", is_flag=True, help="Flash even if the block's serial differs from the ECU's (F18C).")
@click.option("--motor", "motor_file", type=click.Path(dir_okay=False),
              help="Motor TOML overriding the paper preset: its current rating bounds the block, and its type "
                   "(poles, N_enc, f_pwm) is the ECU's when the ECU has no active block to read it from.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
@handle_errors
@exchange_log_options
@io_paths(inputs=("block_file", "key_file", "can_config", "motor_file"))
def flash_cmd(block_file: str, interface: str | None, channel: str | None, bitrate: int | None,
              can_config: str | None, key_file: str | None, key_algo: str | None, verify: bool,
              dry_run: bool, force: bool, motor_file: str | None, as_json: bool) -> None:
    """Write parameter BLOCK (raw .bin or Intel .hex) into the ECU's inactive bank.

    Sequence of firmware contract v1 section 3; the block's sequence becomes the ECU's active
    sequence + 1. The previous block stays active in every failure. Exit 0 flashed and
    verified, 1 verification failed, 2 error or refused.
    """
    from eol_cal.ecu.client import flash_block
    from eol_cal.firmware.block import read_block_file
    from eol_cal.domain.motor_params import load_motor

    data = read_block_file(block_file)
    motor = load_motor("paper", motor_file)
    seed_to_key = key_from_options(key_file, key_algo)
    bus = open_cli_bus(interface, channel, bitrate, can_config)
    try:
        report = flash_block(bus, data, seed_to_key=seed_to_key, verify=verify, dry_run=dry_run,
                             force=force, source=block_file, motor=motor,
                             progress=None if as_json else lambda s: err_console.print(f"  {s}", style="dim"))
    finally:
        bus.shutdown()
    if as_json:
        print_json({"schema": "eol-cal/flash/1", **report.to_dict()})
        return
    prev = f"bank {report.previous.bank} seq {report.previous.sequence}" if report.previous.has_bank else "none"
    if report.dry_run:
        click.echo(f"dry run: ECU {report.serial} would get bank {report.bank} seq {report.sequence} "
                      f"crc {report.crc32:08x} ({report.block_bytes} bytes); active now: {prev}")
        return
    click.echo(f"flashed ECU {report.serial}: bank {report.bank} seq {report.sequence} crc {report.crc32:08x} "
                  f"({report.block_bytes} bytes, {report.transfer_blocks} transfer blocks, "
                  f"{'verified' if report.verified else 'NOT read back'}, {report.seconds:.2f} s, "
                  f"{report.retries} retries); previous: {prev}")


@click.group("ecu")
def ecu_group() -> None:
    """Talk to the ECU: identification, read-back, and restoring an earlier calibration."""


@ecu_group.command("info")
@bus_options
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
@handle_errors
@exchange_log_options
@io_paths(inputs=("can_config",))
def info_cmd(interface: str | None, channel: str | None, bitrate: int | None, can_config: str | None,
             as_json: bool) -> None:
    """Serial, software version, supported layouts, active bank and sequence, and the active block."""
    from eol_cal.ecu.client import ecu_info

    bus = open_cli_bus(interface, channel, bitrate, can_config)
    try:
        info = ecu_info(bus)
    finally:
        bus.shutdown()
    doc = info.to_dict()
    if as_json:
        print_json({"schema": "eol-cal/ecu-info/1", **doc})
        return
    click.echo(f"serial      {doc['serial']}\nsw version  {doc['sw_version']}\n"
                  f"layouts     {doc['layouts']}")
    a = doc["active"]
    if a["bank"] is None:
        click.echo("active      none (no valid bank: the firmware runs uncompensated)")
        return
    click.echo(f"active      bank {a['bank']} seq {a['sequence']} layout {a['layout_version']} crc {a['crc32']}")
    blk = doc["block"]
    if blk and blk["valid"]:
        from eol_cal.rendering.display import to_display

        click.echo(f"block       serial {blk['serial']} table_len {blk['table_len']} k6 {to_display(blk['k6'], 'N*m/A'):.6g} "
                   f"mN*m/A phase_k6 {to_display(blk['phase_k6'], 'rad'):.2f} deg c6 {to_display(blk['c6'], 'N*m'):.6g} "
                   f"mN*m lead {blk['lead_s'] * 1e6:.1f} us iqc_limit {blk['iqc_limit']:g} A flags 0x{blk['flags']:x} "
                   f"calibrated_at {blk['calibrated_at']}")
    elif blk:
        click.echo(f"block       INVALID read-back: {'; '.join(blk['reasons'])}")


@ecu_group.command("read-block")
@bus_options
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Block file to write (raw).")
@click.option("--bank", default=None, metavar="0|1|previous", help="Read this bank instead of the active one.")
@handle_errors
@exchange_log_options
@io_paths(inputs=("can_config",), outputs=("output",))
def read_block_cmd(interface: str | None, channel: str | None, bitrate: int | None, can_config: str | None,
                   output: str, bank: str | None) -> None:
    """Read the active block (or a bank's) back from the ECU into a file (written atomically)."""
    from eol_cal.infra.atomic import atomic_write
    from eol_cal.ecu.client import read_active_block
    from eol_cal.ecu.reflash import read_bank_block
    from eol_cal.firmware.block import check

    which = bank_choice(bank)
    bus = open_cli_bus(interface, channel, bitrate, can_config)
    try:
        data = read_active_block(bus) if which is None else read_bank_block(bus, which).data
    finally:
        bus.shutdown()
    if which is not None and not check(data).valid:
        err_console.print(f"warning: bank {bank}'s block is not valid: {'; '.join(check(data).reasons)}")
    try:
        atomic_write(output, data)
    except OSError as exc:
        raise InputError(output, None, f"cannot write: {exc}") from exc
    click.echo(f"wrote {len(data)} bytes to {output}")


def bank_choice(value: str | None) -> int | str | None:
    from eol_cal.ecu.reflash import PREVIOUS

    if value is None or value == PREVIOUS:
        return value
    if value not in ("0", "1"):
        raise InputError(None, "bank", f"{value!r}: 0, 1 or {PREVIOUS}")
    return int(value)


@click.command("ecu-sim")
@click.option("--flash-file", required=True, type=click.Path(dir_okay=False),
              help="Flash image of both banks (created erased if missing; a restart sees it).")
@click.option("--listen", default="127.0.0.1:54701", show_default=True,
              help="HOST:PORT of the python-can-remote server (port 0: any free port).")
@click.option("--serial", default="SIM-0001", show_default=True, help="Motor serial answered on DID F18C.")
@click.option("--key-file", type=click.Path(dir_okay=False),
              help="The simulated ECU's secret (hex); default the contract's development secret.")
@click.option("--erase-s", type=float, default=0.05, show_default=True, help="Sector erase time, s.")
@click.option("--s3-s", type=float, default=5.0, show_default=True, help="Session timeout S3, s.")
@click.option("--lockout-s", type=float, default=10.0, show_default=True, help="Security lock-out delay, s.")
@click.option("--die-at", metavar="STEP[:N]",
              help="Fault test: the process kills itself (SIGKILL) when the N-th request (default 1) of STEP "
                   "arrives (session, security, read_did, erase, download, transfer, transfer_exit, check, "
                   "read_memory, reset); erase and transfer leave their damage in the flash first.")
@click.option("--slow", metavar="STEP:S", help="Fault test: every request of STEP takes S seconds more (0x78 meanwhile).")
@click.option("--stale-answers", is_flag=True,
              help="Fault test: before each request's answer, the previous answer again (a late duplicate at every step).")
@click.option("--bitrate", type=click.IntRange(10_000, 8_000_000), default=None,
              help="Pace the simulator's bus to this CAN bit rate (bit/s, both directions) [default: unpaced].")
@handle_errors
def ecu_sim_cmd(flash_file: str, listen: str, serial: str, key_file: str | None, erase_s: float,
                s3_s: float, lockout_s: float, die_at: str | None, slow: str | None, stale_answers: bool,
                bitrate: int | None) -> None:
    """Run the ECU simulator, served to other processes over python-can-remote.

    Testers connect with ``--interface remote --channel ws://HOST:PORT/``. Stop with Ctrl-C.
    """
    import os
    import signal
    import threading

    from eol_cal.ecu import protocol as P
    from eol_cal.ecu.client import load_key_file
    from eol_cal.sim.remote_ecu import serve_remote
    from eol_cal.ecu.sim_ecu import STEPS, Faults, SimConfig

    def step_arg(text: str, option: str, kind: type) -> tuple[str, Any]:
        step, _, value = text.partition(":")
        if step not in STEPS:
            raise InputError(None, option, f"step {step!r} is not one of {', '.join(STEPS)}")
        try:
            return step, kind(value) if value else kind(1)
        except ValueError:
            raise InputError(None, option, f"{value!r} after the step is not a {kind.__name__}") from None

    faults = Faults(stale_answers=stale_answers)
    if die_at:
        faults.power_loss_step, faults.power_loss_occurrence = step_arg(die_at, "die-at", int)
    if slow:
        faults.slow_step = dict([step_arg(slow, "slow", float)])

    from eol_cal.infra.address import parse_host_port

    host, port = parse_host_port(listen, "listen", any_port=True)
    try:
        serial.encode("ascii")
    except UnicodeEncodeError:
        raise InputError(None, "serial", f"{serial!r} is not ASCII") from None
    config = SimConfig(serial=serial, secret=load_key_file(key_file) if key_file else P.DEV_SECRET,
                       erase_s=erase_s, s3_s=s3_s, lockout_s=lockout_s, bitrate=bitrate)
    try:
        ecu = serve_remote(flash_file, host=host, port=port, config=config, faults=faults)
    except OSError as exc:
        raise InputError(None, "listen", f"cannot listen on {listen}: {exc}") from exc
    if die_at:
        ecu.sim.on_power_loss = lambda: os.kill(os.getpid(), signal.SIGKILL)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    click.echo(f"ecu-sim: ECU {serial} on {ecu.url} (flash {flash_file}); "
               f"connect with --interface remote --channel {ecu.url}", err=True)
    click.echo(ecu.url, nl=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        ecu.close()


COMMANDS = [flash_cmd, ecu_group, ecu_sim_cmd]
