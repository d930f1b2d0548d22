"""``eol-cal block show|check|hex|a2l``: inspect, validate and export calibration parameter blocks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from cli.common import console, estimator_bits, estimator_option, handle_errors, print_json, styled
from cli.paths import io_paths
from eol_cal.firmware.contract import DEFAULT_TABLE_LEN
from eol_cal.firmware.contract import CHECK_STATUS

#: the check routine's status codes as the contract words them
_STATUS_TEXT = {st.code: st.text for st in CHECK_STATUS.values()}


#: the ``schema`` of ``block show --json`` and ``block check --json``
BLOCK_SHOW_SCHEMA = "eol-cal/block-show/1"
BLOCK_CHECK_SCHEMA = "eol-cal/block-check/1"


def block_report(path: str) -> tuple[dict[str, Any], Any]:
    """The ``block show --json`` document for a file, and the decoded block (None if undecodable)."""
    from eol_cal.errors import InputError
    from eol_cal.firmware import block as B

    data = B.read_block_file(path)
    res = B.check(data)
    try:
        blk = B.unpack(data, path)
        decode_error = None
    except InputError as exc:
        blk, decode_error = None, str(exc)
    doc = {
        "schema": BLOCK_SHOW_SCHEMA,
        "file": str(path),
        "bytes": len(data),
        "valid": res.valid,
        "status": res.status,
        "status_text": _STATUS_TEXT[res.status],
        "reasons": list(res.reasons),
        "warnings": list(res.warnings),
        "crc32_stored": None if res.crc_stored is None else f"0x{res.crc_stored:08x}",
        "crc32_computed": None if res.crc_computed is None else f"0x{res.crc_computed:08x}",
        "block": None if blk is None else blk.to_dict(),
        "decode_error": decode_error,
    }
    return doc, blk


def _print_human(doc: dict[str, Any], blk: Any) -> None:
    import math

    from rich.table import Table

    style = "green" if doc["valid"] else "red"
    console.print(styled(f"{doc['file']}: ", (doc["status_text"], style), f" (status {doc['status']}), "
                         f"{doc['bytes']} bytes"))
    for r in doc["reasons"]:
        console.print(styled("  ", ("invalid:", "red"), f" {r}"))
    for w in doc["warnings"]:
        console.print(styled("  ", ("warning:", "yellow"), f" {w}"))
    if doc["crc32_stored"] is not None:
        console.print(f"  crc32 stored {doc['crc32_stored']}, computed {doc['crc32_computed']}")
    if blk is None:
        console.print(f"  not decodable: {doc['decode_error']}")
        return
    d = doc["block"]
    table = Table(show_header=True, header_style="bold")
    table.add_column("field")
    table.add_column("value")
    table.add_column("unit")
    from eol_cal.rendering.display import display_unit
    from eol_cal.firmware.block import FIELDS, flag_names

    for name, spec in FIELDS.items():
        if name in ("table_const", "table_per_amp", "crc32"):
            continue
        v = d.get(name)
        if name == "magic":
            text = f"0x{v:04x}"
        elif name == "flags":
            text = f"0x{v:x} ({flag_names(v)})"
        elif name == "hall_angle":
            text = ", ".join(f"{math.degrees(a):.2f}°" for a in v)
        elif name == "reserved":
            continue
        elif isinstance(v, float):
            unit, factor = display_unit(spec.get("unit", ""))  # one unit per quantity: k6 in mN*m/A...
            text = f"{v * factor:.9g}"
        else:
            text = str(v)
        if name == "hall_angle":
            unit = "deg (electrical)"
        elif not isinstance(v, float):
            unit = spec.get("unit", "")
        table.add_row(name, text, unit)
    for name in ("table_const", "table_per_amp"):
        arr = getattr(blk, name)
        table.add_row(name, f"{arr.size} entries, min {arr.min():.6g}, max {arr.max():.6g}",
                      FIELDS[name].get("unit", ""))
    console.print(table)


@click.group("block")
def block_group() -> None:
    """Inspect, check and export calibration parameter blocks (firmware contract, section 2).

    FILE is a raw block or bank image (bytes after the block are allowed), or an Intel HEX file
    at a bank's address.
    """


@block_group.command("show")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="one JSON document on stdout (tables included)")
@handle_errors
def show(file: str, as_json: bool) -> None:
    """Fields, validity with reasons, and CRC of a block (exit 2 when it cannot be decoded)."""
    from eol_cal.errors import InputError

    doc, blk = block_report(file)
    if as_json:
        print_json(doc)
    else:
        _print_human(doc, blk)
    if blk is None:
        raise InputError(file, None, "not a decodable parameter block (reason above)")


def unsafe_reasons(data: bytes, file: str, motor_file: str | None) -> list[str]:
    """Why a block that the firmware calls valid must still not drive the motor (empty: it may).

    The physical-sanity rules of :mod:`eol_cal.firmware.block_sanity` for the motor of
    ``motor_file`` (default the paper preset): finite values, currents within its rating, its type.
    """
    from eol_cal.firmware import block as B
    from eol_cal.firmware.block_sanity import MotorType, sanity_problems, type_problems
    from eol_cal.domain.motor_params import load_motor

    motor = load_motor("paper", motor_file)
    blk = B.unpack(data, file)
    problems = sanity_problems(blk, motor.i_max) + type_problems(blk, MotorType.of_motor(motor))
    return [f"{f}: {r}" for f, r in problems]


_MOTOR_OPTION = click.option("--motor", "motor_file", type=click.Path(dir_okay=False),
                             help="Motor TOML overriding the paper preset: its current rating i_max and its type "
                                  "(poles, N_enc, f_pwm) the block must fit.")


@block_group.command("check")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="one JSON document on stdout")
@_MOTOR_OPTION
@handle_errors
@io_paths(inputs=("file", "motor_file"))
def check_cmd(file: str, as_json: bool, motor_file: str | None) -> None:
    """Apply the firmware's check routine, then the physical-sanity rules (finite values, currents
    within the motor's rating, the motor's type); exit 0 valid and safe, 1 invalid or unsafe, 2 unreadable."""
    from eol_cal.errors import CheckFailed
    from eol_cal.firmware import block as B

    data = B.read_block_file(file)
    res = B.check(data)
    unsafe = unsafe_reasons(data, file, motor_file) if res.valid else []
    if as_json:
        print_json({"schema": BLOCK_CHECK_SCHEMA, "file": file, "valid": res.valid, "status": res.status,
                    "status_text": _STATUS_TEXT[res.status], "reasons": list(res.reasons),
                    "warnings": list(res.warnings), "safe": res.valid and not unsafe, "unsafe": unsafe})
    elif res.valid and not unsafe:
        click.echo(f"{file}: valid" + "".join(f"\n  warning: {w}" for w in res.warnings))
    if not res.valid:
        raise CheckFailed(f"{file}: {_STATUS_TEXT[res.status]} (status {res.status}): " + "; ".join(res.reasons))
    if unsafe:
        raise CheckFailed(f"{file}: valid for the firmware but unsafe for the motor: " + "; ".join(unsafe))


@block_group.command("hex")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--bank", type=click.IntRange(0, 1), required=True, help="target bank: 0 (sector C) or 1 (sector B)")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Intel HEX file to write")
@_MOTOR_OPTION
@handle_errors
@io_paths(inputs=("file", "motor_file"), outputs=("output",))
def hex_cmd(file: str, bank: int, output: str, motor_file: str | None) -> None:
    """Write a valid block as Intel HEX at its bank's flash address (byte address = 2 x word address).

    Refuses an invalid or unsafe block (exit 1). Bytes after the block are not exported.
    """
    from eol_cal.errors import CheckFailed
    from eol_cal.firmware import block as B
    from eol_cal.infra.atomic import atomic_write

    data = B.read_block_file(file)
    res = B.check(data)
    if not res.valid:
        raise CheckFailed(f"{file}: refusing to export an invalid block: " + "; ".join(res.reasons))
    unsafe = unsafe_reasons(data, file, motor_file)
    if unsafe:
        raise CheckFailed(f"{file}: refusing to export an unsafe block: " + "; ".join(unsafe))
    n = B.unpack(data, file).table_len
    text = B.to_intel_hex(data[:B.block_bytes(n)], bank)
    atomic_write(Path(output), text.encode("ascii"))
    start = B.BANK_BYTE_ADDR[bank]
    click.echo(f"wrote {output}: {B.block_bytes(n)} bytes at byte address 0x{start:x} "
               f"(word address 0x{B.BANK_WORD_ADDR[bank]:x}, bank {bank})")


@block_group.command("a2l")
@click.option("--bank", type=click.IntRange(0, 1), required=True,
              help="bank whose addresses the characteristics carry: 0 (sector C) or 1 (sector B)")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="A2L file to write")
@click.option("--table-len", type=int, default=DEFAULT_TABLE_LEN, show_default=True,
              help="table entries N the file describes (power of two, 16..1024; eol-cal table's default)")
@click.option("--layout", type=click.IntRange(1, 2), default=2, show_default=True,
              help="layout version: 2 (revision 1.2, the mechanical-order extension; what eol-cal table writes) or 1")
@handle_errors
@io_paths(outputs=("output",))
def a2l_cmd(bank: int, output: str, table_len: int, layout: int) -> None:
    """Write the A2L description (ASAP2 1.71) of a block in a bank for CANape/INCA.

    Addresses are byte addresses (2 x word address, as in the Intel HEX files); both banks'
    MEMORY_SEGMENTs are described. The tables' and the CRC's addresses depend on N: a block
    with another table length needs its own file.
    """
    from eol_cal.infra.atomic import atomic_write
    from eol_cal.firmware.gen_a2l import bank_byte_address, render_a2l

    text = render_a2l(bank, table_len, layout)
    atomic_write(Path(output), text.encode("ascii"))
    click.echo(f"wrote {output}: layout {layout}, bank {bank} at byte address 0x{bank_byte_address(bank):x}, "
               f"table_len {table_len}")


@block_group.command("uncompensated")
@click.option("--serial", required=True, help="Motor serial (1-16 ASCII characters).")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="block image to write (.bin)")
@click.option("--motor", "motor_file", type=click.Path(dir_okay=False),
              help="Motor TOML overriding the paper preset (poles, N_enc, f_pwm).")
@estimator_option("give the calibrated block's, so the motor is measured under the estimator it will run.")
@handle_errors
@io_paths(inputs=("motor_file",), outputs=("output",))
def uncompensated_cmd(serial: str, output: str, motor_file: str | None, estimator: str) -> None:
    """Write the block a motor is measured under: the interpolated angle, no compensation.

    Flash it before the calibration capture (`eol-cal flash`) when running the steps one by one,
    as `eol-cal run` does in its first step: a blank ECU would run the raw encoder angle, a
    calibrated one its old compensation.
    """
    from eol_cal.analysis.fit.table import uncompensated_block
    from eol_cal.infra.atomic import atomic_write
    from eol_cal.firmware import block as B
    from eol_cal.domain.motor_params import load_motor

    blk = uncompensated_block(serial, load_motor("paper", motor_file), options=estimator_bits(estimator))
    data = B.pack(blk)
    atomic_write(Path(output), data)
    click.echo(f"wrote {output}: {len(data)} bytes, flags {B.flag_names(blk.flags)} (no compensation), "
               f"serial {serial}")


COMMANDS = [block_group]
