"""The per-motor report: one self-contained HTML page from the run record and the run's data.

Top: serial, variant, station, operator, times, the verdict. Then every limit of the variant
as a row (value, limit, margin, PASS/FAIL), the ECU state before and after, and the plots,
inline SVG: torque against electrical angle before and compensated on one scale with the fitted
ripple; the order spectrum before and compensated with the limits; the fit's residual of every
segment as small multiples. What the record lacks (a run that ended early, a field that older
records do not have) is shown as such, never guessed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from eol_cal.render import plain
from eol_cal.report.svg import figure_svg, pyplot
from eol_cal.station.limits import LimitCheck, Measured, VariantLimits, limit_checks, measured_from_fit

if TYPE_CHECKING:
    from eol_cal.analysis.fit import FitSpec, MotorFit
    from eol_cal.analysis.fit.capture import MotorInput
    from eol_cal.analysis.spectrum import OrderSpectrum
    from eol_cal.analysis.point_metrics import PointRipple

#: the fit of one motor as the report draws it: its inputs, its fit and the model
FitExtra = tuple["MotorInput", "MotorFit", "FitSpec"]
#: the ripple at the operating point, before and compensated
PointRipples = tuple["PointRipple", "PointRipple"]
from eol_cal.wrap import wrap_2pi

_MAX_POINTS = 3000  # points drawn per panel: enough to show the band, small enough to inline
_ANGLE_BINS = 120  # 3 deg electrical per bin for the mean curve
_MAX_ORDER = 24
NO_STATION = "(no station id)"


@dataclass(frozen=True)
class Figure:
    """One plot of a page.

    Attributes
    ----------
    name : str
        Unique on the page: the SVG's id prefix and the figure's anchor.
    caption : str
        What it shows, in words.
    svg : str
        The inline ``<svg>`` element.
    """

    name: str
    caption: str
    svg: str


def drawn(name: str, draw: Callable[[], Figure]) -> Figure:
    """``draw()``, or, when drawing fails, a figure that says why on the page.

    A plot that cannot be drawn must not cost the motor its record or its verdict (the report
    step's failure would make the run an error); the page shows the reason instead.
    """
    try:
        return draw()
    except Exception as exc:  # noqa: BLE001 - shown on the page, the run goes on
        from xml.sax.saxutils import escape

        return Figure(name, f"not drawn: {type(exc).__name__}: {exc}",
                      f'<p class="plot-error">This plot could not be drawn: {escape(type(exc).__name__)}: '
                      f"{escape(str(exc))}</p>")


@dataclass(frozen=True)
class LimitRow:
    """A limit row of the report: the check and how it is shown (``PASS``, ``FAIL``, ``not measured``)."""

    check: LimitCheck
    status: str


# --------------------------------------------------------------------------- from the record
def limits_of(rec: dict[str, Any]) -> VariantLimits | None:
    """The variant's limits as the record keeps them (None when it has none)."""
    lim = rec.get("limits") or {}
    names = [f.name for f in fields(VariantLimits)]
    try:
        return VariantLimits(**{k: lim[k] for k in names if k in lim})
    except TypeError:
        return None


def measured_of(rec: dict[str, Any]) -> Measured:
    """What the record says was measured, NaN where it was not (a run that ended early)."""
    nan = math.nan
    met = rec.get("metrics") or {}
    try:
        m = measured_from_fit(rec["fit"])
    except (KeyError, TypeError, ValueError):
        m = Measured(k6=nan, ci_k6=nan, ci_phase_k6_deg=nan, ci_c6_nm=nan, r2=nan, rms_nm=nan)
    pp = {k: float(met[k]) if met.get(k) is not None else nan for k in ("pp_before_pct", "pp_after_pct", "pp_after_no_mech1_pct")}
    return Measured(**{**m.__dict__, **pp})


def limit_rows(rec: dict[str, Any]) -> list[LimitRow]:
    """Every limit of the record's variant against what the record measured.

    A NaN value is ``FAIL`` when the run's verdict names it (a hall table that could not be
    measured fails the motor), otherwise ``not measured`` (the run ended before that step).
    """
    lim = limits_of(rec)
    if lim is None:
        return []
    reasons = set(rec.get("reasons") or [])
    rows = []
    for c in limit_checks(measured_of(rec), lim):
        if c.ok:
            status = "PASS"
        elif math.isfinite(c.value) or c.reason in reasons:
            status = "FAIL"
        else:
            status = "not measured"
        rows.append(LimitRow(c, status))
    return rows


def station_of(rec: dict[str, Any]) -> str:
    """The station a run was made on: its id where the record has one."""
    st = rec.get("station") or {}
    for value in (rec.get("station_id"), st.get("id"), st.get("station_id"), st.get("name")):
        if value:
            return str(value)
    return NO_STATION


def ecu_states(rec: dict[str, Any]) -> list[dict[str, str]]:
    """The ECU's state before the run (the pre-flight's read), after the prepare step, after the
    calibration flash, and the block it ran during each capture (read over UDS before it).

    One dict per column with the keys ``label``, ``bank``, ``sequence``, ``crc32``, ``flags``,
    ``estimator`` (the estimator options the block's flags select: ``paper``, ``best`` or their
    names), ``verified``; a value the record does not have is ``"-"``.
    """
    def text(x: object) -> str:
        return "-" if x is None else ("yes" if x is True else "no" if x is False else str(x))

    prep = rec.get("ecu_prepared") or {}
    blk = rec.get("block") or {}
    flash = rec.get("flash") or {}
    # the pre-flight's read of the ECU has the flags and the CRC as well
    found = ((rec.get("preflight") or {}).get("ecu") or {}).get("state")
    before = rec.get("ecu_before") or found or prep.get("previous") or {}
    # the prepare step's read of the ECU says bank None when no bank was valid (a blank ECU)
    before_bank = "none valid" if "bank" in before and before["bank"] is None else before.get("bank")
    cols = [
        {"label": "before the run", "bank": before_bank, "sequence": before.get("sequence"),
         "crc32": before.get("crc32"), "flags": before.get("flags"), "estimator": before.get("estimator"),
         "verified": None},
        {"label": "prepared (uncompensated)", "bank": prep.get("bank"), "sequence": prep.get("sequence"),
         "crc32": prep.get("crc32"), "flags": prep.get("flags"), "estimator": prep.get("estimator"),
         "verified": prep.get("verified")},
        {"label": "calibrated", "bank": blk.get("bank"), "sequence": blk.get("sequence"), "crc32": blk.get("crc32"),
         "flags": blk.get("flags"), "estimator": blk.get("estimator"), "verified": flash.get("verified")},
    ]
    for which, label in (("before", "ran during the calibration capture"), ("after", "ran during the compensated capture")):
        ran = ((rec.get("captures") or {}).get(which) or {}).get("ecu_before")
        if isinstance(ran, dict):  # read over UDS before that acquisition (the same after it, or the cycle erred)
            cols.append({"label": label, "bank": "none valid" if ran.get("bank") is None else ran["bank"],
                         "sequence": ran.get("sequence"), "crc32": ran.get("crc32"), "flags": ran.get("flags"),
                         "verified": None})
    after = rec.get("ecu_after")
    if isinstance(after, dict):  # read back from the ECU where the record has it
        cols.append({"label": "read back after the run", **{k: after.get(k) for k in ("bank", "sequence", "crc32",
                                                                                         "flags", "estimator", "verified")}})
    return [{k: text(v) if k != "label" else v for k, v in c.items()} for c in cols]


def _estimator_text(rec: dict[str, Any]) -> str:
    """The estimator the calibrated block runs, and the one the motor was measured under."""
    blk = (rec.get("block") or {}).get("estimator")
    prep = (rec.get("ecu_prepared") or {}).get("estimator")
    if blk is None and prep is None:
        return "-"
    text = f"{blk or '-'} (block flags bits 2-5)"
    if prep is not None and prep != blk:
        text += f"; measured under {prep}"
    return text


# --------------------------------------------------------------------------- plots
def _decimate(*arrays: np.ndarray, n: int = _MAX_POINTS) -> list[np.ndarray]:
    step = max(1, len(arrays[0]) // n)
    return [np.asarray(a)[::step] for a in arrays]


def _binned_mean(deg: np.ndarray, y: np.ndarray, bins: int = _ANGLE_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``y`` in equal bins of electrical angle (deg, 0..360); empty bins dropped."""
    k = np.minimum((deg / 360.0 * bins).astype(int), bins - 1)
    n = np.bincount(k, minlength=bins)
    s = np.bincount(k, weights=y, minlength=bins)
    centre = (np.arange(bins) + 0.5) * 360.0 / bins
    ok = n > 0
    return centre[ok], s[ok] / n[ok]


def _without_mech1(theta_r: np.ndarray, torque: np.ndarray, spectrum: OrderSpectrum, pole_pairs: int) -> np.ndarray:
    """Torque minus its mean and its mechanical order 1 (the rotor's unbalance, which no table
    cancels), using the capture's own order spectrum (``A cos(theta_m + phase)``)."""
    y = np.asarray(torque, float) - float(np.mean(torque))
    a, ph = float(spectrum.mech1_amplitude_nm), float(spectrum.mech1_phase_rad)
    if math.isfinite(a) and math.isfinite(ph):
        y = y - a * np.cos(np.asarray(theta_r, float) / pole_pairs + ph)
    return y


def operating_segment(mi: MotorInput, speed_rpm: float, i_qo_a: float) -> int:
    """Index of the fit segment nearest the operating point (speed in rpm, i_qo in A, signed)."""
    def distance(s: int) -> float:
        info = mi.info[s]
        return (abs(info.i_qo - i_qo_a) / max(abs(i_qo_a), 1.0)
                + abs(info.speed_rpm - speed_rpm) / max(abs(speed_rpm), 1.0))

    return min(range(len(mi.info)), key=distance)


def angle_figure(rec: dict[str, Any], point_ripple: PointRipples, fit_extra: FitExtra | None) -> Figure:
    """Torque against electrical angle at the operating point, before and compensated, one scale.

    Parameters
    ----------
    rec : dict
        The run record (operating point).
    point_ripple : (PointRipple, PointRipple)
        Before and compensated (:class:`eol_cal.analysis.point_metrics.PointRipple`, with ``theta_r``).
    fit_extra : (MotorInput, MotorFit, FitSpec) or None
        The fit, for the fitted ripple drawn over both.
    """
    from eol_cal.analysis.fit.plot import fitted_ripple

    plt = pyplot()
    op = (rec.get("fit") or {}).get("operating_point") or (rec.get("metrics") or {}).get("operating_point") or {}
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.3), sharey=True)
    curve = None
    if fit_extra is not None and op:
        mi, fit, spec = fit_extra
        s = operating_segment(mi, float(op["speed_rpm"]), float(op["i_qo_a"]))
        grid = np.linspace(0.0, 2 * math.pi, 361)
        curve = (np.degrees(grid), fitted_ripple(mi, fit, spec, s, grid) - float(fit.t_avg[s]))
    for ax, pr, label in zip(axes, point_ripple, ("before", "compensated")):
        pole_pairs = max(1, int(pr.poles) // 2)
        y = _without_mech1(pr.theta_r, pr.torque, pr.spectrum, pole_pairs)
        deg = np.degrees(wrap_2pi(np.asarray(pr.theta_r, float)))
        d_deg, d_y = _decimate(deg, y)
        ax.plot(d_deg, d_y, ".", ms=1.2, color="0.65", alpha=0.6, label="measured", rasterized=True)
        cx, cy = _binned_mean(deg, y)
        ax.plot(cx, cy, "-", color="tab:blue", lw=1.4, label="mean over 3 deg")
        if curve is not None:
            ax.plot(*curve, "--" if label == "compensated" else "-", color="tab:red", lw=1.3,
                    label="fitted ripple" + (" (before, for reference)" if label == "compensated" else ""))
        ax.set_title(f"{label}: p-p {pr.pp_pct:.2f} % (filtered)", fontsize=9)
        ax.set_xlim(0, 360)
        ax.set_xticks(range(0, 361, 60))
        ax.set_xlabel("electrical angle theta_r (deg)", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, loc="upper right")
    axes[0].set_ylabel("torque - mean (N*m)", fontsize=8)
    where = f"{op.get('speed_rpm', float('nan')):.0f} rpm, i_qo {op.get('i_qo_a', float('nan')):.0f} A" if op else ""
    fig.suptitle(f"{plain(rec['serial'])}: torque at the operating point ({where}), mean and mechanical order 1 removed",
                 fontsize=9)
    fig.tight_layout()
    return Figure("angle", "Torque against electrical angle at the operating point, before and with the "
                  "compensation, on one scale, with the fitted ripple", figure_svg(fig, "angle"))


def spectrum_figure(rec: dict[str, Any], point_ripple: PointRipples) -> Figure:
    """Order spectrum before and compensated with the limits as lines.

    Two limits are drawn in N*m: ``max_pp_after_pct`` of the mean torque as the amplitude of one
    order alone (a sine of amplitude A has p-p 2A), and ``max_k6 * |i_qo|`` at order 6 (the
    load-proportional part of the 6th the variant allows).
    """
    plt = pyplot()
    lim = rec.get("limits") or {}
    op = (rec.get("metrics") or {}).get("operating_point") or {}
    fig, ax = plt.subplots(figsize=(10, 3.0))
    width = 0.38
    for off, pr, label, colour in ((-width / 2, point_ripple[0], "before", "tab:blue"),
                                   (width / 2, point_ripple[1], "compensated", "tab:green")):
        sp = pr.spectrum
        keep = sp.orders <= _MAX_ORDER
        ax.bar(sp.orders[keep] + off, sp.amplitude_nm[keep], width=width, color=colour, label=label)
    t_avg = abs(float(point_ripple[0].T_avg_nm))
    if lim.get("max_pp_after_pct") is not None and t_avg > 0:
        a = lim["max_pp_after_pct"] / 100.0 * t_avg / 2.0
        ax.axhline(a, color="tab:red", lw=1.0, ls="--",
                   label=f"max_pp_after_pct {lim['max_pp_after_pct']:g} % as one order's amplitude ({a:.3g} N*m)")
    if lim.get("max_k6") is not None and op.get("i_qo_a") is not None:
        a6 = lim["max_k6"] * abs(float(op["i_qo_a"]))
        ax.plot([5.5, 6.5], [a6, a6], color="tab:orange", lw=2.0,
                label=f"max_k6 x |i_qo| at order 6 ({a6:.3g} N*m)")
    ax.set_yscale("log")
    ax.set_xlim(0.3, _MAX_ORDER + 0.7)
    ax.set_xticks(range(1, _MAX_ORDER + 1))
    ax.set_xlabel("electrical order", fontsize=8)
    ax.set_ylabel("amplitude (N*m)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return Figure("spectrum", "Order spectrum of the torque at the operating point, before and with the "
                  "compensation, with the limits", figure_svg(fig, "spectrum"))


def residual_figure(fit_extra: FitExtra, cols: int = 4) -> Figure:
    """The fit's residual (measured - model) against electrical angle, one small panel per
    segment: every segment, shared scale.

    Parameters
    ----------
    fit_extra : (MotorInput, MotorFit, FitSpec)
        The motor's fit inputs, its fit and the model.
    cols : int
        Panels per row.
    """
    from eol_cal.analysis.fit.plot import segment_model

    plt = pyplot()
    mi, fit, spec = fit_extra
    n = mi.segments.n_segments
    cols = max(1, min(cols, n))
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(10, 1.55 * rows + 0.4), sharex=True, sharey=True, squeeze=False)
    seg = mi.segments
    for s in range(n):
        ax = axes[s // cols][s % cols]
        ax.set_gid(f"segment-{s + 1}")  # one panel per segment, countable on the page
        model, _ = segment_model(mi, fit, spec, s)
        r = np.asarray(seg.torque[s], float) - model
        deg = np.degrees(wrap_2pi(np.asarray(seg.theta[s], float)))
        d_deg, d_r = _decimate(deg, r, n=1500)
        ax.plot(d_deg, d_r, ".", ms=0.8, color="0.5", rasterized=True)
        rms = float(np.sqrt(np.mean(r ** 2)))
        info = mi.info[s]
        ax.set_title(f"{s + 1}: {info.speed_rpm:.0f} rpm, {info.i_qo:.0f} A, rms {rms * 1e3:.1f} mN*m", fontsize=6.5)
        ax.set_xlim(0, 360)
        ax.set_xticks(range(0, 361, 120))
        ax.tick_params(labelsize=6)
        ax.grid(alpha=0.3)
    for s in range(n, rows * cols):
        axes[s // cols][s % cols].axis("off")
    fig.supxlabel("electrical angle theta_r (deg)", fontsize=7)
    fig.supylabel("residual (N*m)", fontsize=7)
    fig.tight_layout(pad=0.4)
    return Figure("residual", f"Fit residual against electrical angle, each of the {n} segments "
                  f"(fit rms {fit.rms * 1e3:.2f} mN*m)", figure_svg(fig, "residual"))


# --------------------------------------------------------------------------- the page
def _fmt(x: float | None, digits: int = 4) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{float(x):.{digits}g}"


def render_motor_report(rec: dict[str, Any], figures: Sequence[Figure]) -> str:
    """The per-motor page (self-contained HTML) of a run record and its figures."""
    from eol_cal.report.page import render

    fit = rec.get("fit") or {}
    st = rec.get("station") or {}
    hall = fit.get("hall_angle") or {}
    values = [
        ("k6", f"{_fmt((fit.get('k6') or {}).get('value'))} ± {_fmt((fit.get('k6') or {}).get('ci95'), 2)} N*m/A"),
        ("phase_k6", f"{_fmt(math.degrees(v)) if (v := (fit.get('phase_k6') or {}).get('value')) is not None else '-'} deg"),
        ("c6", f"{_fmt((fit.get('c6') or {}).get('value'))} N*m"),
        ("hall table", hall.get("source", "-") if hall.get("source") != "measured" else
         "measured, offsets " + " ".join(f"{d:+.2f}" for d in hall.get("deviation_deg", [])) + " deg"),
        ("compensated p-p, mech. order 1 taken out",
         f"{_fmt((rec.get('metrics') or {}).get('pp_after_no_mech1_pct'))} % "
         + ("(no limit: the rest is the rotor's unbalance)" if (rec.get("limits") or {}).get("max_pp_after_no_mech1_pct") is None
            else f"(limit {_fmt(rec['limits']['max_pp_after_no_mech1_pct'])} %: the rows below)")),
        ("lead", f"{_fmt((rec.get('block') or {}).get('lead_s', None) and rec['block']['lead_s'] * 1e6)} us"),
        ("estimator options", _estimator_text(rec)),
    ]
    ecu = rec.get("ecu_active") or {}
    captures = rec.get("captures") or {}
    return render("motor.html.j2", rec=rec, station=st, figures=list(figures), limit_rows=limit_rows(rec),
                  ecu_states=ecu_states(rec), ecu_active=ecu, values=values, fmt=_fmt,
                  operator=rec.get("operator") or st.get("operator"),
                  station_name=station_of(rec) if station_of(rec) != NO_STATION else st.get("dyno"),
                  captures=captures, total_s=sum(s.get("seconds") or 0.0 for s in rec.get("steps") or []))
