"""Everything ``eol-cal analyze`` reports for one capture: ripple, spectrum, quantisation, angle.

The report is a plain JSON-ready dict whose keys are documented in ``docs/json.md``; the CLI
prints it as a table or as JSON, the station and scripts use it directly.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from eol_cal.analysis.angle import capture_angle
from eol_cal.analysis.metrics import capture_ripple_pp
from eol_cal.analysis.plots import CapturePlotData
from eol_cal.analysis.spectrum import capture_spectrum, quantisation_figures
from eol_cal.infra.jsonsafe import json_safe

if TYPE_CHECKING:
    from eol_cal.capture.data import Capture

#: orders shown in the table (electrical); mechanical order 1 is added separately
TOP_ORDERS = (6, 12, 18)


def analyze_capture(capture: Capture, ripple_options: dict[str, Any] | None = None, fw_angle: bool = False) -> tuple[dict, Any]:
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
    angle = capture_angle(capture)
    ripple = capture_ripple_pp(capture, angle, **(ripple_options or {}))
    # The spectrum of the longest steady run: one operating point, whole revolutions.
    seg = max(ripple.segments, key=lambda s: s[1] - s[0])
    spectrum = capture_spectrum(capture, angle, span_s=(seg[0], seg[1] + 0.5 / capture.sample_rate))
    quant = quantisation_figures(capture, angle)
    T_avg = ripple.T_avg_nm

    def order_entry(amp: float, phase: float) -> dict:
        pct = 100.0 * amp / abs(T_avg) if T_avg else float("nan")
        return {"amplitude_nm": json_safe(float(amp)), "amplitude_pct": json_safe(float(pct)),
                "phase_rad": json_safe(float(phase))}

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
            "raw_pct": json_safe(float(ripple.raw_pct)),
            "filtered_pct": json_safe(float(ripple.filtered_pct)),
            "raw_pct_max": json_safe(float(ripple.raw_pct_max)),
            "filtered_pct_max": json_safe(float(ripple.filtered_pct_max)),
            "no_mech1_pct": json_safe(float(ripple.no_mech1_pct)),
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
                    "raw_pct": json_safe(float(w.raw_pct)),
                    "filtered_pct": json_safe(float(w.filtered_pct)),
                    "no_mech1_pct": json_safe(float(w.no_mech1_pct)),
                    "speed_rpm": w.speed_rpm,
                    "i_qo_a": json_safe(float(w.i_qo_a)),
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
            "mech1_amplitude_nm": json_safe(float(spectrum.mech1_amplitude_nm)),
            "mech1_phase_rad": json_safe(float(spectrum.mech1_phase_rad)),
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
        from eol_cal.analysis.firmware_angle import firmware_angle_difference

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
