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
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence

import numpy as np

from eol_cal.rendering.display import display_unit
from eol_cal.rendering.figures import pyplot
from eol_cal.rendering.renderer import plain
from eol_cal.report.svg import figure_svg
from eol_cal.records.record import NO_STATION
from eol_cal.numerics.wrap import wrap_2pi

if TYPE_CHECKING:
    from eol_cal.analysis.fit import FitSpec, MotorFit
    from eol_cal.capture.ecu_state import EcuState
    from eol_cal.records.record import RunRecord
    from eol_cal.analysis.fit.motor_input import MotorInput
    from eol_cal.analysis.spectrum import OrderSpectrum
    from eol_cal.analysis.point_metrics import PointRipple

#: the fit of one motor as the report draws it: its inputs, its fit and the model
FitExtra = tuple["MotorInput", "MotorFit", "FitSpec"]
#: the ripple at the operating point, before and compensated
PointRipples = tuple["PointRipple", "PointRipple"]

_MAX_POINTS = 3000  # points drawn per panel: enough to show the band, small enough to inline
_ANGLE_BINS = 120  # 3 deg electrical per bin for the mean curve
_MAX_ORDER = 24


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
    """A limit row of the report: the record's check in its display unit (:mod:`eol_cal.rendering.display`)
    and how it is shown (``PASS``, ``FAIL``, ``not measured``, ``not judged``)."""

    key: str
    title: str
    sense: str
    value: float
    limit: float
    margin: float
    unit: str
    status: str


# --------------------------------------------------------------------------- from the record
def limit_rows(rec: RunRecord) -> list[LimitRow]:
    """The record's checks as rows, display units; nothing is judged here.

    A check the cycle judged is ``PASS`` or ``FAIL``; one it did not reach is ``not measured``
    when it has no value, ``not judged`` when it has one.
    """
    rows = []
    for c in rec.checks:
        unit, factor = display_unit(c.unit)
        if c.passed is not None:
            status = "PASS" if c.passed else "FAIL"
        else:
            status = "not measured" if math.isnan(c.value) else "not judged"
        rows.append(LimitRow(c.key, c.title, c.sense, c.value * factor, c.limit * factor, c.margin * factor, unit, status))
    return rows


def _state_col(label: str, s: EcuState | None, verified: bool | None = None) -> dict[str, Any]:
    if s is None:
        return {"label": label}
    return {"label": label, "bank": "none valid" if s.bank is None else s.bank, "sequence": s.sequence, "crc32": s.crc32,
            "flags": s.flags, "verified": verified}


def ecu_states(rec: RunRecord) -> list[dict[str, str]]:
    """The ECU's state before the run (the pre-flight's read), each block the run flashed, and
    the block it ran during each capture (read over UDS before it).

    One dict per column with the keys ``label``, ``bank``, ``sequence``, ``crc32``, ``flags``,
    ``estimator`` (the estimator options the block's flags select: ``paper``, ``best`` or their
    names), ``verified``; a value the record does not have is ``"-"``.
    """
    def text(x: object) -> str:
        return "-" if x is None else ("yes" if x is True else "no" if x is False else str(x))

    cols: list[dict[str, Any]] = []
    found = rec.preflight.ecu.state if rec.preflight is not None and rec.preflight.ecu is not None else None
    if found is not None:
        cols.append(_state_col("before the run", found))
    else:
        prev = next((b.previous for b in rec.blocks if b.previous is not None), None)
        cols.append({"label": "before the run", "bank": None if prev is None else
                     ("none valid" if prev.bank is None else prev.bank), "sequence": None if prev is None else prev.sequence})
    labels = {"prepare": "prepared (uncompensated)", "calibrated": "calibrated", "restore": "restored"}
    for b in rec.blocks:
        cols.append({"label": labels[b.role] + ("" if b.confirmed else " (not confirmed)"), "bank": b.bank,
                     "sequence": b.sequence, "crc32": b.crc32, "flags": b.flags, "estimator": b.estimator,
                     "verified": b.verified})
    for which, label in (("before", "ran during the calibration capture"), ("after", "ran during the compensated capture")):
        c = rec.captures.get(which)
        if c is not None and c.ecu_before is not None:
            cols.append(_state_col(label, c.ecu_before))
    keys = ("bank", "sequence", "crc32", "flags", "estimator", "verified")
    return [{"label": c["label"], **{k: text(c.get(k)) for k in keys}} for c in cols]


def _estimator_text(rec: RunRecord) -> str:
    """The estimator the calibrated block runs, and the one the motor was measured under."""
    blk, prep = rec.block("calibrated"), rec.block("prepare")
    if blk is None and prep is None:
        return "-"
    text = f"{(blk.estimator if blk else None) or '-'} (block flags bits 2-5)"
    if prep is not None and prep.estimator != (blk.estimator if blk else None):
        text += f"; measured under {prep.estimator}"
    return text


# --------------------------------------------------------------------------- plots
def _margins(fig: Any, *, left: float, right: float, bottom: float, top: float, wspace: float = 0.0,
             hspace: float = 0.0) -> None:
    """The subplots' margins and gaps in inches (gaps between panels, not fractions of them).

    The report's figures have fixed sizes and fonts, so fixed margins hold their labels; the
    figure is drawn once, when it is written. ``tight_layout`` drew each figure once more to
    measure it: 40 % of the report's CPU, which runs beside the next motor's cycle.
    """
    w, h = fig.get_size_inches()
    gs = fig.axes[0].get_gridspec() if fig.axes else None
    rows, cols = (gs.nrows, gs.ncols) if gs is not None else (1, 1)
    span_w, span_h = w - left - right, h - bottom - top
    panel_w, panel_h = (span_w - (cols - 1) * wspace) / cols, (span_h - (rows - 1) * hspace) / rows
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=wspace / panel_w, hspace=hspace / panel_h)


#: digits and minus as superscripts (a decade's exponent, :func:`_log_tick`)
_SUPERSCRIPT = str.maketrans("-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079")


def _log_tick(value: float, _pos: object = None) -> str:
    """A decade's label as 10 with a superscript exponent in plain text: matplotlib's default
    spells it as math text, whose parser cost 0.3 s a process for the spectrum's few labels."""
    exponent = round(math.log10(value)) if value > 0 else 0
    return "10" + str(exponent).translate(_SUPERSCRIPT)


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


def angle_figure(rec: RunRecord, point_ripple: PointRipples, fit_extra: FitExtra | None) -> Figure:
    """Torque against electrical angle at the operating point, before and compensated, one scale.

    Parameters
    ----------
    rec : RunRecord
        The run record (operating point).
    point_ripple : (PointRipple, PointRipple)
        Before and compensated (:class:`eol_cal.analysis.point_metrics.PointRipple`, with ``theta_r``).
    fit_extra : (MotorInput, MotorFit, FitSpec) or None
        The fit, for the fitted ripple drawn over both.
    """
    from eol_cal.analysis.fit.plot import fitted_ripple

    plt = pyplot()
    op = {}
    if rec.fit is not None:
        op = {"speed_rpm": rec.fit.operating_point.speed_rpm, "i_qo_a": rec.fit.operating_point.i_qo_a}
    elif rec.metrics is not None:
        op = {"speed_rpm": rec.metrics.speed_rpm, "i_qo_a": rec.metrics.i_qo_a}
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.3), sharey=True)
    curve = None
    if fit_extra is not None and op:
        mi, fit, spec = fit_extra
        s = operating_segment(mi, float(op["speed_rpm"]), float(op["i_qo_a"]))
        grid = np.linspace(0.0, 2 * math.pi, 361)
        curve = (np.degrees(grid), fitted_ripple(mi, fit, spec, s, grid) - float(fit.t_avg[s]))
    for ax, pr, label in zip(axes, point_ripple, ("before", "compensated"), strict=True):
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
    fig.suptitle(f"{plain(rec.serial)}: torque at the operating point ({where}), mean and mechanical order 1 removed",
                 fontsize=9)
    _margins(fig, left=0.75, right=0.12, bottom=0.48, top=0.62, wspace=0.3)
    return Figure("angle", "Torque against electrical angle at the operating point, before and with the "
                  "compensation, on one scale, with the fitted ripple", figure_svg(fig, "angle"))


def spectrum_figure(rec: RunRecord, point_ripple: PointRipples) -> Figure:
    """Order spectrum before and compensated with the limits as lines.

    Two of the record's limits are drawn in N*m: the compensated p-p limit (%) of the mean torque
    as the amplitude of one order alone (a sine of amplitude A has p-p 2A), and the k6 limit times
    |i_qo| at order 6 (the load-proportional part of the 6th the variant allows).
    """
    plt = pyplot()
    pp_after, k6 = rec.check("pp_after_pct"), rec.check("k6")
    fig, ax = plt.subplots(figsize=(10, 3.0))
    width = 0.38
    for off, pr, label, colour in ((-width / 2, point_ripple[0], "before", "tab:blue"),
                                   (width / 2, point_ripple[1], "compensated", "tab:green")):
        sp = pr.spectrum
        keep = sp.orders <= _MAX_ORDER
        ax.bar(sp.orders[keep] + off, sp.amplitude_nm[keep], width=width, color=colour, label=label)
    t_avg = abs(float(point_ripple[0].T_avg_nm))
    if pp_after is not None and t_avg > 0:
        a = pp_after.limit / 100.0 * t_avg / 2.0
        ax.axhline(a, color="tab:red", lw=1.0, ls="--",
                   label=f"{pp_after.key} {pp_after.limit:g} % as one order's amplitude ({a:.3g} N*m)")
    if k6 is not None and rec.metrics is not None:
        a6 = k6.limit * abs(rec.metrics.i_qo_a)
        unit, factor = display_unit(k6.unit)
        ax.plot([5.5, 6.5], [a6, a6], color="tab:orange", lw=2.0,
                label=f"{k6.key} {k6.limit * factor:g} {unit} x |i_qo| at order 6 ({a6:.3g} N*m)")
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(_log_tick)
    ax.set_xlim(0.3, _MAX_ORDER + 0.7)
    ax.set_xticks(range(1, _MAX_ORDER + 1))
    ax.set_xlabel("electrical order", fontsize=8)
    ax.set_ylabel("amplitude (N*m)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper right")
    _margins(fig, left=0.75, right=0.12, bottom=0.45, top=0.1)
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
    _margins(fig, left=0.78, right=0.12, bottom=0.45, top=0.2, wspace=0.2, hspace=0.3)
    return Figure("residual", f"Fit residual against electrical angle, each of the {n} segments "
                  f"(fit rms {fit.rms * 1e3:.2f} mN*m)", figure_svg(fig, "residual"))


# --------------------------------------------------------------------------- the page
def _fmt(x: float | None, digits: int = 4) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{float(x):.{digits}g}"


def _estimate(est: Any, unit: str, digits: int = 4) -> str:
    """An estimate ``value ± ci95`` in its display unit."""
    if est is None:
        return "-"
    shown, factor = display_unit(unit)
    ci = "" if est.ci95 is None else f" ± {_fmt(est.ci95 * factor, 2)}"
    return f"{_fmt(est.value * factor, digits)}{ci} {shown}"


def mech_section(rec: RunRecord) -> dict[str, Any] | None:
    """The report's mechanical orders (contract revision 1.2): the block's switch, the identification
    margin, each order fitted, and order 1 before and with the compensation (None without a
    mechanical result)."""
    m = rec.fit.mech if rec.fit is not None else None
    if m is None:
        return None
    cal = rec.block("calibrated")
    switch = cal.mech if cal is not None and cal.mech is not None else ("written" if cal is None else "not in the block")
    least_cos = "" if m.min_score is None else f" (least {_fmt(m.min_score, 3)})"
    status = (f"MECH_COMP_ENABLE {switch}: predicted identification margin {_fmt(m.margin, 3)} (least {_fmt(m.threshold, 3)}), "
              f"cosine {_fmt(m.score, 3)}{least_cos}, one revolution at {_fmt(m.ref_rpm, 3)} rpm; fingerprint "
              + {1: "forward", 2: "reverse", 3: "forward and reverse"}.get(m.dirs, "not measured")
              + ("" if not m.reasons else "; off: " + "; ".join(m.reasons)))
    before = rec.metrics.before.mech1_nm if rec.metrics is not None else None
    after = rec.metrics.after.mech1_nm if rec.metrics is not None else None
    rows = []
    for o in m.orders:
        amp = _estimate(o.c, "N*m")
        fitted = f"{amp}, phase {_estimate(o.phase_c, 'rad', 3)}" + (f" ({o.no_interval})" if o.no_interval else "")
        left = (f"{_fmt(after * 1e3, 3)} mN*m (uncompensated {_fmt(before * 1e3, 3)} mN*m)"
                if o.order == 1 and after is not None and before is not None else "-")  # both None without metrics
        rows.append((o.order, fitted, left))
    return {"status": status, "rows": rows}


def render_motor_report(rec: RunRecord, figures: Sequence[Figure]) -> str:
    """The per-motor page (self-contained HTML) of a run record and its figures."""
    from eol_cal.report.html import render

    e = rec.fit.estimates if rec.fit is not None else None
    hall = (rec.fit.hall_angle if rec.fit is not None else None) or {}
    no_mech1 = rec.check("pp_after_no_mech1_pct")
    cal = rec.block("calibrated")
    values = [
        ("k6", _estimate(e and e.k6, "N*m/A")),
        ("phase_k6", _estimate(e and e.phase_k6, "rad")),
        ("c6", _estimate(e and e.c6, "N*m")),
        ("hall table", hall.get("source", "-") if hall.get("source") != "measured" else
         "measured, offsets " + " ".join(f"{d:+.2f}" for d in hall.get("deviation_deg", [])) + " deg"),
        ("compensated p-p, mech. order 1 taken out",
         f"{_fmt(rec.metrics.after.pp_no_mech1_pct if rec.metrics else None)} % "
         + ("(the mechanical orders are compensated too: below)" if cal is not None and cal.mech == "on"
            else "(no limit: the rest is the rotor's unbalance)" if no_mech1 is None
            else f"(limit {_fmt(no_mech1.limit)} %: the rows below)")),
        ("lead", f"{_fmt(cal.lead_s * 1e6 if cal is not None and cal.lead_s is not None else None)} us"),
        ("estimator options", _estimator_text(rec)),
    ]
    name = rec.station_label
    return render("motor.html.j2", rec=rec, station=rec.station, figures=list(figures), limit_rows=limit_rows(rec),
                  ecu_states=ecu_states(rec), ecu_active=rec.ecu_active, values=values, fmt=_fmt, mech=mech_section(rec),
                  operator=rec.operator, station_name=name if name != NO_STATION else rec.station.extra.get("dyno"),
                  captures=rec.captures, total_s=rec.total_s)
