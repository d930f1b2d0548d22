"""``eol-cal analyze``: ripple metrics, order spectrum and angle quantisation per capture."""

from __future__ import annotations

import click

from cli.common import console, handle_errors, print_json
from cli.paths import io_paths
from eol_cal.errors import InputError

def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _ecu_text(ecu: dict | None) -> str:
    """The ECU state of a report in a few words (``-``: not recorded)."""
    if ecu is None:
        return "-"
    b = ecu["ecu_before"]
    if b["bank"] is None:
        return "no block"
    return f"seq {b['sequence']} {b['crc32']}\n{b['flags']}"


def _print_table(reports: list[dict]) -> None:
    from rich.table import Table

    from eol_cal.analysis.analyze import TOP_ORDERS

    table = Table(title="eol-cal analyze")
    table.add_column("", style="bold")
    for r in reports:
        table.add_column(r["file"], justify="right", overflow="fold")
    rows = [
        ("serial", lambda r: r["serial"]),
        # a capture with several speeds (or both directions) shows each
        ("speed rpm", lambda r: ", ".join(f"{v:g}" for v in sorted({round(w["speed_rpm"], 1)
                                                                    for w in r["ripple"]["windows"]}))),
        ("T_avg N*m", lambda r: f"{r['T_avg_nm']:.4f}"),
        ("p-p raw %", lambda r: _fmt(r["ripple"]["raw_pct"], ".2f")),
        ("p-p filtered %", lambda r: _fmt(r["ripple"]["filtered_pct"], ".2f")),
        ("windows x el. revs", lambda r: f"{r['ripple']['n_windows']} x {r['ripple']['window_revs']}"),
        ("eta % (eq. 12)", lambda r: f"{r['eta_pct']:.3g}"),
    ]
    for key in [str(n) for n in TOP_ORDERS] + ["mech1"]:
        label = f"order {key} N*m (%)" if key != "mech1" else "mech. order 1 N*m (%)"
        rows.append((label, lambda r, k=key: f"{_fmt(r['top_orders'][k]['amplitude_nm'], '.4f')} "
                                             f"({_fmt(r['top_orders'][k]['amplitude_pct'], '.2f')})"))
    rows += [
        ("el. deg/count", lambda r: f"{r['quantisation']['deg_per_count']:.3f}"),
        ("raw enc. error rms/max deg",
         lambda r: f"{r['quantisation']['enc_error_rms_deg']:.2f} / {r['quantisation']['enc_error_max_deg']:.2f}"),
        ("hall residual rms deg", lambda r: f"{r['angle']['hall_residual_rms_deg']:.2f}"),
        ("ECU", lambda r: _ecu_text(r["ecu"])),
    ]
    if any("firmware_angle" in r for r in reports):
        rows.append(("fw estimator - offline rms/max deg",
                     lambda r: f"{r['firmware_angle']['rms_deg']:.3f} / {r['firmware_angle']['max_deg']:.3f}"
                     if "firmware_angle" in r else "-"))
        rows.append(("fw 6th phase shift deg",
                     lambda r: f"{r['firmware_angle']['phase6_shift_deg']:.3f}" if "firmware_angle" in r else "-"))
    for label, get in rows:
        table.add_row(label, *[get(r) for r in reports])
    console.print(table)


@click.command("analyze")
@click.argument("captures", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--map", "map_file", type=click.Path(dir_okay=False), help="Channel map (TOML) for foreign files.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON (keys in docs/json.md).")
@click.option("--plot", "plot_file", type=click.Path(dir_okay=False),
              help="Write torque against time and the order spectrum, a row per capture, to this PNG.")
@click.option("--fw-angle", is_flag=True,
              help="Also run the firmware's angle estimator (JAX; seconds) and report it against the offline angle.")
@handle_errors
@io_paths(inputs=("captures", "map_file"), outputs=("plot_file",))
def analyze_cmd(captures: tuple[str, ...], map_file: str | None, as_json: bool, plot_file: str | None,
                fw_angle: bool) -> None:
    """Ripple metrics (p-p % raw and filtered), order spectrum and encoder quantisation per CAPTURE.

    A joined capture (``eol-cal acquire``: metadata segment_starts) is reported per window (FILE#k).

    Exit code 2 when any capture is refused (the others are still reported).

    The ECU state recorded in a capture (metadata ecu_before/ecu_after) is reported with it; a
    capture under compensation is analysed (that is how the compensated ripple is measured), one
    whose ECU block changed during the acquisition is refused, one with no record is analysed
    with a warning.
    """
    from eol_cal.analysis.analyze import analyze_capture
    from eol_cal.capture import load_channel_map, read_capture
    from eol_cal.capture.ecu_state import check_trace, trace_of
    from eol_cal.capture.windows import split_windows

    channel_map = load_channel_map(map_file) if map_file else None
    reports: list[dict] = []
    plots = []
    errors: list[dict] = []
    for path in captures:
        try:
            capture = read_capture(path, channel_map)
            trace = trace_of(capture.metadata, path)
            warnings = check_trace(trace, path, allow_untraced=True, allow_compensated=True)
            if not trace.traced:  # under compensation is what this command is for: no warning
                click.echo(f"warning: {warnings[0]}", err=True)
            windows = split_windows(capture)
        except InputError as exc:
            windows = []
            errors.append({"file": exc.file or path, "field": exc.field, "reason": exc.reason})
            click.echo(f"error: {exc}", err=True)  # one line, never wrapped
        # a joined (dyno) capture is reported window by window: no angle across a join
        for window in windows:
            try:
                report, plot = analyze_capture(window, fw_angle=fw_angle)
            except InputError as exc:
                errors.append({"file": exc.file or window.source, "field": exc.field, "reason": exc.reason})
                click.echo(f"error: {exc}", err=True)  # one line, never wrapped
                continue
            report["ecu"] = trace.to_dict() if trace.traced else None
            reports.append(report)
            plots.append(plot)
    if plot_file and plots:
        from eol_cal.analysis.plots import plot_captures

        plot_captures(plot_file, plots)
    if as_json:
        print_json({"schema": "eol-cal/analyze/1", "captures": reports, "errors": errors,
                    "plot": plot_file if plots else None})
    elif reports:
        _print_table(reports)
        if plot_file:
            console.print(f"plot written: {plot_file}")
    if errors:
        raise SystemExit(2)


COMMANDS = [analyze_cmd]
