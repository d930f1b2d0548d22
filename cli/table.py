"""``eol-cal table``: compensator tables from a fit result, packed into a parameter block."""

from __future__ import annotations

import click

from cli.common import console, estimator_bits, estimator_option, handle_errors, print_json, styled
from cli.paths import io_paths
from eol_cal.firmware.contract import DEFAULT_TABLE_LEN


def _lead(text: str) -> float | None:
    if text == "auto":
        return None
    try:
        value = float(text)
    except ValueError:
        raise click.BadParameter(f"{text!r}: 'auto' or a time in seconds") from None
    if not (value >= 0.0 and value < 0.1):
        raise click.BadParameter(f"{value}: a lead in seconds, 0 <= lead < 0.1")
    return value


@click.command("table")
@click.argument("result", type=click.Path(dir_okay=False))
@click.option("--serial", help="Motor to take from a result with several.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Block image to write (.bin).")
@click.option("--table-len", default=DEFAULT_TABLE_LEN, show_default=True, type=int,
              help="Table entries N (power of two, 16..1024).")
@click.option("--lead", "lead", default="auto", show_default=True,
              help="Look-up lead: 'auto' (current-loop lag at the operating speed) or seconds.")
@click.option("--iqc-limit", type=click.FloatRange(0.0), help="Clamp of |i_qc| (A); default 10 % of the largest |i_qo| fitted.")
@click.option("--motor", "motor_file", type=click.Path(dir_okay=False),
              help="Motor TOML overriding the paper preset (current_bw_hz, f_cc, f_pwm).")
@click.option("--hex", "hex_file", type=click.Path(dir_okay=False), help="Also write Intel HEX at the bank's flash address.")
@click.option("--bank", default=0, show_default=True, type=click.IntRange(0, 1), help="Bank address for --hex.")
@estimator_option("the block's flags carry them (the ECU runs that estimator).")
@click.option("--layout", type=click.IntRange(1, 2), default=2, show_default=True,
              help="2: with the mechanical orders and the encoder's fingerprint (revision 1.2; MECH_COMP_ENABLE "
                   "when the identification margin passes); 1: the block of revision 1.1.")
@click.option("--json", "as_json", is_flag=True, help="Print the block's fields as JSON.")
@handle_errors
@io_paths(inputs=("result", "motor_file"), outputs=("output", "hex_file"))
def table_cmd(result, serial, output, table_len, lead, iqc_limit, motor_file, hex_file, bank, estimator, layout, as_json):
    """Build the compensator tables of one motor and pack them into a valid parameter block.

    Layout 2 (the default) also carries the encoder's fingerprint and the mechanical orders; its
    MECH_COMP_ENABLE stays off, with the reason printed, when the fit's identification margin is
    too small. Exit 1 when the motor's fit is not usable, 2 on bad input.
    """
    from eol_cal.analysis.fit.table import block_from_result, created_unix, mech_off_reasons, select_motor
    from eol_cal.analysis.motor_result import MotorResult
    from eol_cal.analysis.result import read_result
    from eol_cal.infra.atomic import atomic_write
    from eol_cal.errors import naming
    from eol_cal.firmware.block import check, flag_names, pack, to_intel_hex
    from eol_cal.firmware.options import options_label
    from eol_cal.firmware.block_sanity import require_safe
    from eol_cal.domain.motor_params import load_motor

    lead_s = _lead(lead)
    options = estimator_bits(estimator)
    doc = read_result(result)
    rec = select_motor(doc, serial, result)
    motor_result = MotorResult.from_json(rec, result, f"motors[{doc['motors'].index(rec)}].")
    motor = load_motor("paper", motor_file)
    with naming(result):  # the tables' and the block's own checks see values; they came from RESULT
        blk = block_from_result(motor_result, motor, table_len=table_len, lead_s=lead_s, iqc_limit=iqc_limit,
                                calibrated_at=created_unix(doc, str(result)), source=result, options=options, layout=layout)
        data = pack(blk)
    res = check(data)
    if not res.valid:  # pack() refuses bad fields; this guards the layout code itself
        raise RuntimeError(f"packed block does not check: {res.reasons}")
    require_safe(blk, motor, result)  # e.g. --iqc-limit 1e30: above the motor's current rating
    atomic_write(output, data)
    if hex_file:
        atomic_write(hex_file, to_intel_hex(data, bank))
    mech_off = mech_off_reasons(motor_result, blk.flags) if layout == 2 else []
    if as_json:
        d = blk.to_dict()
        d.pop("table_const")
        d.pop("table_per_amp")
        if "mech" in d:
            for name in ("mech_table_const", "mech_table_per_amp"):
                d["mech"].pop(name)
        print_json({"schema": "eol-cal/table/1", "file": output, "bytes": len(data), "block": d,
                    "mech_off_reasons": mech_off})
    else:
        console.print(
            f"{blk.serial}: {len(data)} bytes -> {output}; N = {blk.table_len}, lead {blk.lead_s * 1e6:.1f} us"
            f"{' (auto)' if lead_s is None else ''}, iqc_limit {blk.iqc_limit:.3g} A, "
            f"max |table_per_amp| {abs(blk.table_per_amp).max():.3g} A/A, max |table_const| {abs(blk.table_const).max():.3g} A; "
            f"hall_angle {(motor_result.hall_angle or {}).get('source', 'nominal')}; "
            f"estimator {options_label(options)} (flags {flag_names(blk.flags)})"
        )
        if layout == 2:
            m = motor_result.mech
            console.print(f"layout 2: MECH_COMP_ENABLE {'off' if mech_off else 'on'}"
                          + (f" (identification margin {m.margin:.3f}, threshold {m.threshold:g}; order 1 "
                             f"{m.orders[0].c.value * 1e3:.2f} mN*m)" if m is not None and m.orders else "")
                          + ("" if not mech_off else "; " + "; ".join(mech_off)))
        frame_estimator = (motor_result.model or {}).get("frame_estimator")
        if frame_estimator is not None and frame_estimator != options_label(options):
            console.print(styled(("warning:", "yellow"), f" the fit measured its phases' frame under the "
                                 f"{frame_estimator} estimator; the block runs {options_label(options)}"))


COMMANDS = [table_cmd]
