"""``eol-cal analyze``: ripple metrics, order spectrum and angle quantisation per capture."""

from __future__ import annotations

import math
from typing import Any

import click

from cli.common import console, err_console, handle_errors, print_json
from eol_cal.errors import InputError

#: orders shown in the table (electrical); mechanical order 1 is added separately
TOP_ORDERS = (6, 12, 18)


def _finite(x: float) -> float | None:
    """JSON has no NaN: undefined figures become null."""
    return float(x) if math.isfinite(x) else None


def analyze_capture(capture, ripple_options: dict[str, Any] | None = None, fw_angle: bool = False) -> tuple[dict, Any]:
    """Every figure ``eol-cal analyze`` reports for one capture.

    Parameters
    ----------
    capture : Capture
        A validated capture.
    ripple_options : dict, optional
        Keyword arguments for :func:`eol_cal.analysis.metrics.ripple_pp`.
    fw_angle : bool
        Also run the firmware's estimator (JAX) and report its angle against the offline one.

    Returns
    -------
    report : dict
        The capture's JSON object (keys in ``docs/json.md``).
    plot_data : CapturePlotData
        What the figure draws for this capture.
    """
    import numpy as np

    from eol_cal.analysis.angle import capture_angle
    from eol_cal.analysis.metrics import capture_ripple_pp
    from eol_cal.analysis.plots import CapturePlotData
    from eol_cal.analysis.spectrum import capture_spectrum, quantisation_figures

    angle = capture_angle(capture)
    ripple = capture_ripple_pp(capture, angle, **(ripple_options or {}))
    # The spectrum of the longest steady run: one operating point, whole revolutions.
    seg = max(ripple.segments, key=lambda s: s[1] - s[0])
    spectrum = capture_spectrum(capture, angle, span_s=(seg[0], seg[1] + 0.5 / capture.sample_rate))
    quant = quantisation_figures(capture, angle)
    T_avg = ripple.T_avg_nm

    def order_entry(amp: float, phase: float) -> dict:
        pct = 100.0 * amp / abs(T_avg) if T_avg else float("nan")
        return {"amplitude_nm": _finite(amp), "amplitude_pct": _finite(pct), "phase_rad": _finite(phase)}

    top = {str(n): order_entry(spectrum.amplitude(n), spectrum.phase(n)) for n in TOP_ORDERS}
    top["mech1"] = order_entry(spectrum.mech1_amplitude_nm, spectrum.mech1_phase_rad)
    report = {
        "file": capture.source,
        "serial": capture.serial,
        "poles": capture.poles,
        "encoder_ppr": capture.encoder_ppr,
        "speed_rpm": ripple.speed_rpm,
        "T_avg_nm": T_avg,
        "ripple": {
            "raw_pct": _finite(ripple.raw_pct),
            "filtered_pct": _finite(ripple.filtered_pct),
            "raw_pct_max": _finite(ripple.raw_pct_max),
            "filtered_pct_max": _finite(ripple.filtered_pct_max),
            "raw_pp_nm": ripple.raw_pp_nm,
            "filtered_pp_nm": ripple.filtered_pp_nm,
            "window_revs": ripple.window_revs,
            "n_windows": len(ripple.windows),
            "cutoff_order": ripple.cutoff_order,
            "n_spikes": ripple.n_spikes,
            "segments_s": [list(s) for s in ripple.segments],
            "windows": [
                {
                    "t_start": w.t_start,
                    "t_end": w.t_end,
                    "n_revs": w.n_revs,
                    "T_avg_nm": w.T_avg_nm,
                    "raw_pct": _finite(w.raw_pct),
                    "filtered_pct": _finite(w.filtered_pct),
                    "speed_rpm": w.speed_rpm,
                    "i_qo_a": _finite(w.i_qo_a),
                }
                for w in ripple.windows
            ],
        },
        "eta_pct": quant.eta_pct,
        "top_orders": top,
        "spectrum": {
            "orders": [int(n) for n in spectrum.orders],
            "amplitude_nm": [float(a) for a in spectrum.amplitude_nm],
            "phase_rad": [float(p) for p in spectrum.phase_rad],
            "mech1_amplitude_nm": _finite(spectrum.mech1_amplitude_nm),
            "mech1_phase_rad": _finite(spectrum.mech1_phase_rad),
            "n_elec_revs": spectrum.n_elec_revs,
            "span_s": list(spectrum.span_s),
        },
        "quantisation": {
            "deg_per_count": quant.deg_per_count,
            "deg_per_edge": quant.deg_per_edge,
            "enc_error_rms_deg": quant.enc_error_rms_deg,
            "enc_error_max_deg": quant.enc_error_max_deg,
        },
        "angle": {
            "offset_rad": angle.offset_rad,
            "hall_residual_rms_deg": float(np.rad2deg(angle.hall_residual_rms_rad)),
            "hall_residual_max_deg": float(np.rad2deg(angle.hall_residual_max_rad)),
            "n_edges": angle.n_edges,
            "n_hall_edges": angle.n_hall_edges,
            "direction": angle.direction,
        },
    }
    if fw_angle:
        from eol_cal.analysis.angle import firmware_angle_difference

        d = firmware_angle_difference(capture, angle)
        report["firmware_angle"] = {
            "mean_deg": d.mean_deg,
            "rms_deg": d.rms_deg,
            "max_deg": d.max_deg,
            "raw_rms_deg": d.raw_rms_deg,
            "raw_max_deg": d.raw_max_deg,
            "phase6_shift_deg": d.phase6_shift_deg,
            "n_ticks": d.n_ticks,
        }
    plot = CapturePlotData(
        label=f"{capture.source} ({capture.serial})",
        t=capture.t,
        torque=capture["torque"],
        poles=capture.poles,
        ripple=ripple,
        spectrum=spectrum,
    )
    return report, plot


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _print_table(reports: list[dict]) -> None:
    from rich.table import Table

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
def analyze_cmd(captures: tuple[str, ...], map_file: str | None, as_json: bool, plot_file: str | None,
                fw_angle: bool) -> None:
    """Ripple metrics (p-p % raw and filtered), order spectrum and encoder quantisation per CAPTURE.

    A joined capture (``eol-cal acquire``: metadata segment_starts) is reported per window (FILE#k).

    Exit code 2 when any capture is refused (the others are still reported).
    """
    from eol_cal.capture import load_channel_map, read_capture

    channel_map = load_channel_map(map_file) if map_file else None
    reports: list[dict] = []
    plots = []
    errors: list[dict] = []
    from eol_cal.capture.windows import split_windows

    for path in captures:
        try:
            windows = split_windows(read_capture(path, channel_map))
        except InputError as exc:
            windows = []
            errors.append({"file": exc.file or path, "field": exc.field, "reason": exc.reason})
            err_console.print(f"error: {exc}", markup=False, highlight=False)
        # a joined (dyno) capture is reported window by window: no angle across a join
        for window in windows:
            try:
                report, plot = analyze_capture(window, fw_angle=fw_angle)
            except InputError as exc:
                errors.append({"file": exc.file or window.source, "field": exc.field, "reason": exc.reason})
                err_console.print(f"error: {exc}", markup=False, highlight=False)
                continue
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
