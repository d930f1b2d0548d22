"""Figures of the analysis: the ripple index against PPR (seed Fig. 4) and per-capture ripple.

matplotlib is imported inside the functions (Agg backend) so that importing this module is
cheap; every figure is written atomically.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eol_cal.analysis.metrics import RipplePP, eta_percent, lowpass_zero_phase
from eol_cal.analysis.spectrum import OrderSpectrum
from eol_cal.rendering.figures import pyplot, write_png
from eol_cal.rendering.renderer import plain


def plot_eta(path: str | Path, poles: int, ppr: int, ppr_min: int, ppr_max: int, table_ppr: np.ndarray) -> None:
    """Ripple index eta (%) against encoder PPR on a log axis, ``ppr`` highlighted (seed Fig. 4).

    Parameters
    ----------
    path : path
        PNG file to write (atomically).
    poles : int
        Number of poles P.
    ppr : int
        Encoder pulses per revolution to highlight.
    ppr_min, ppr_max : int
        PPR range of the curve.
    table_ppr : ndarray of int
        PPR values marked as points (the table's rows).
    """
    plt = pyplot()
    n = np.unique(np.geomspace(ppr_min, ppr_max, 400).round().astype(int))
    fig, ax = plt.subplots(figsize=(7, 4.2))
    try:
        ax.plot(n, eta_percent(n, poles), color="tab:blue", label=f"eta = 100(1 - cos(P*pi/N_enc)), P = {poles}")
        ax.plot(table_ppr, eta_percent(table_ppr, poles), "o", color="tab:blue", ms=4)
        eta = eta_percent(ppr, poles)
        ax.plot([ppr], [eta], "o", color="tab:red", ms=8, label=f"{ppr} PPR: {eta:.3g} %")
        ax.annotate(f"{ppr} PPR\n{eta:.3g} %", (ppr, eta), textcoords="offset points", xytext=(10, 10), color="tab:red")
        ax.set_xscale("log")
        ax.set_xlabel("encoder pulses per revolution N_enc")
        ax.set_ylabel("torque ripple index eta (%)")
        ax.set_title("Torque ripple from angle quantisation (seed eq. 12, Fig. 4)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        fig.tight_layout()
        write_png(fig, path)
    finally:
        plt.close(fig)


@dataclass(frozen=True, eq=False)
class CapturePlotData:
    """What one row of the analysis figure shows.

    Attributes
    ----------
    label : str
        Row title (file and serial).
    t : ndarray
        Sample times (s).
    torque : ndarray
        Torque (N*m).
    poles : int
        Number of poles P.
    ripple : RipplePP
        Its peak-to-peak result (windows are shaded, the filtered trace uses its cut-off).
    spectrum : OrderSpectrum
        Its order spectrum.
    """

    label: str
    t: np.ndarray
    torque: np.ndarray
    poles: int
    ripple: RipplePP
    spectrum: OrderSpectrum


def plot_captures(path: str | Path, rows: list[CapturePlotData]) -> None:
    """Torque against time and the order spectrum, a row per capture, into one PNG.

    Parameters
    ----------
    path : path
        PNG file to write (atomically).
    rows : list of CapturePlotData
        One entry per capture.
    """
    plt = pyplot()
    fig, axes = plt.subplots(len(rows), 2, figsize=(12, 3.4 * len(rows)), squeeze=False,
                             gridspec_kw={"width_ratios": [3, 2]})
    try:
        for (ax_t, ax_s), row in zip(axes, rows, strict=True):
            r = row.ripple
            fs = (len(row.t) - 1) / (row.t[-1] - row.t[0])
            # one trace for the whole record: the windows' typical |speed| sets its cut-off
            f_e = float(np.median([abs(w.speed_rpm) for w in r.windows])) / 60.0 * row.poles / 2
            filt = lowpass_zero_phase(row.torque, fs, r.cutoff_order * f_e) if f_e > 0 else row.torque
            ax_t.plot(row.t, row.torque, color="0.7", lw=0.5, label="raw")
            ax_t.plot(row.t, filt, color="tab:blue", lw=1.0, label=f"low-pass {r.cutoff_order:g} x f_e")
            for i, w in enumerate(r.windows):
                ax_t.axvspan(w.t_start, w.t_end, color="tab:green", alpha=0.08 if i % 2 else 0.15, lw=0)
            ax_t.set_title(f"{plain(row.label)}: p-p {r.raw_pct:.2f} % raw, {r.filtered_pct:.2f} % filtered, "
                           f"T_avg {r.T_avg_nm:.3f} N*m", fontsize=9)
            ax_t.set_xlabel("t (s)")
            ax_t.set_ylabel("torque (N*m)")
            ax_t.legend(fontsize=7, loc="upper right")
            ax_t.grid(alpha=0.3)
            s = row.spectrum
            ax_s.bar(s.orders, s.amplitude_nm, color=["tab:red" if n % 6 == 0 else "tab:blue" for n in s.orders])
            if np.isfinite(s.mech1_amplitude_nm):
                ax_s.bar([2.0 / row.poles], [s.mech1_amplitude_nm], width=0.25, color="tab:purple",
                         label="mech. order 1")
                ax_s.legend(fontsize=7)
            ax_s.set_yscale("log")
            ax_s.set_xlabel("electrical order")
            ax_s.set_ylabel("amplitude (N*m)")
            ax_s.set_title(f"order spectrum over {s.n_elec_revs} electrical revolutions", fontsize=9)
            ax_s.grid(alpha=0.3, which="both")
        fig.tight_layout()
        write_png(fig, path)
    finally:
        plt.close(fig)
