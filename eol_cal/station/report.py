"""Per-motor report: an HTML page with the PNG plots, plus the run record as JSON.

Written into the run's own directory (next to its captures, fit and block), every file
atomically (temp file in the same directory, fsync, rename), the HTML last: a report page that
exists names only files that exist.

- ``fit.png``: torque against electrical angle with the fitted ripple (``eol_cal.analysis.fit_plot``)
- ``residual.png``: the fit residual's order spectrum
- ``ripple.png``: torque and order spectrum at the operating point, before and with compensation
  (``eol_cal.analysis.plots.plot_captures``)
- ``report.json``: the run record (the same document the database holds)
- ``report.html``: verdict, reasons, figures, step times, and links to everything above
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any

from eol_cal.atomic import atomic_write


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, text)


def _fmt(x: Any, scale: float = 1.0, digits: int = 4) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{float(x) * scale:.{digits}g}"


def _or_dash(x: Any) -> str:
    return "-" if x is None else str(x)


def fit_plots(run_dir: str | Path, fit_extra: Any) -> list[tuple[str, str]]:
    """Write ``fit.png`` and ``residual.png``; returns ``(file name, caption)`` of each.

    Parameters
    ----------
    run_dir : path
        The run's directory.
    fit_extra : (MotorInput, MotorFit, FitSpec)
        The motor's fit inputs, its fit and the model.
    """
    from eol_cal.analysis.fit_plot import plot_fit, plot_residual_spectrum

    run_dir = Path(run_dir)
    mi, fit, spec = fit_extra
    plot_fit(run_dir / "fit.png", mi, fit, spec)
    plot_residual_spectrum(run_dir / "residual.png", mi, fit, spec)
    return [("fit.png", "Torque against electrical angle (drift and mechanical order 1 removed) with the fitted ripple"),
            ("residual.png", "Order spectrum of the fit residual")]


def ripple_plot(run_dir: str | Path, rec: dict[str, Any], point_ripple: Any) -> list[tuple[str, str]]:
    """Write ``ripple.png``: torque and order spectrum at the operating point, before and compensated.

    Parameters
    ----------
    run_dir : path
        The run's directory.
    rec : dict
        The run record (serial, operating point).
    point_ripple : (PointRipple, PointRipple)
        Before and compensated (:class:`eol_cal.station.run.PointRipple`).
    """
    from eol_cal.analysis.plots import CapturePlotData, plot_captures

    op = rec["metrics"]["operating_point"]
    rows = [
        CapturePlotData(label=f"{rec['serial']} {label} ({op['speed_rpm']:.0f} rpm, {op['i_qo_a']:.0f} A)",
                        t=pr.t, torque=pr.torque, poles=pr.poles, ripple=pr.ripple, spectrum=pr.spectrum)
        for label, pr in (("before", point_ripple[0]), ("compensated", point_ripple[1]))
    ]
    plot_captures(Path(run_dir) / "ripple.png", rows)
    return [("ripple.png", "Torque and order spectrum at the operating point: before, and with the compensation")]


def _hall_text(hall: dict[str, Any] | None) -> str:
    """The hall table's line: each boundary's offset from nominal (deg), or why it is nominal."""
    if not hall:
        return "-"
    if hall.get("source") != "measured":
        return str(hall.get("source"))
    return "measured, offsets " + " ".join(f"{d:+.2f}" for d in hall["deviation_deg"]) + " deg (states 1..6)"


def render_html(rec: dict[str, Any], figures: list[tuple[str, str]]) -> str:
    """The report page (self-contained HTML; images by relative file name)."""
    e = html.escape
    v = rec["verdict"]
    colour = {"pass": "#1a7f37", "fail": "#b35900", "error": "#c00"}.get(v, "#000")
    fit = rec.get("fit") or {}
    met = rec.get("metrics") or {}
    lim = rec.get("limits") or {}
    blk = rec.get("block") or {}
    ecu = rec.get("ecu_active") or {}
    rows = [
        ("k6", f"{_fmt((fit.get('k6') or {}).get('value'), 1e3)} ± {_fmt((fit.get('k6') or {}).get('ci95'), 1e3, 2)} mN*m/A",
         f"max {_fmt(lim.get('max_k6'), 1e3)} mN*m/A"),
        ("phase_k6", f"{_fmt(math.degrees((fit.get('phase_k6') or {}).get('value') or math.nan))} deg", ""),
        ("c6", f"{_fmt((fit.get('c6') or {}).get('value'), 1e3)} mN*m", ""),
        ("hall boundaries", _hall_text(fit.get("hall_angle")), f"max {_fmt(lim.get('max_hall_deviation_deg'))} deg"),
        ("fit R^2 / rms", f"{_fmt((fit.get('fit') or {}).get('r2'))} / {_fmt((fit.get('fit') or {}).get('rms'), 1e3)} mN*m",
         f"min {_fmt(lim.get('min_r2'))} / max {_fmt(lim.get('max_rms_nm'), 1e3)} mN*m"),
        ("p-p before", f"{_fmt(met.get('pp_before_pct'))} %", f"max {_fmt(lim.get('max_pp_before_pct'))} %"),
        ("p-p compensated", f"{_fmt(met.get('pp_after_pct'))} %", f"max {_fmt(lim.get('max_pp_after_pct'))} %"),
        ("p-p compensated, mech. order 1 taken out", f"{_fmt(met.get('pp_after_no_mech1_pct'))} %",
         "no limit: what the tables act on (the rest is the rotor's unbalance)"),
        ("improvement", f"{_fmt(met.get('improvement_pct'))} %", f"min {_fmt(lim.get('min_improvement_pct'))} %"),
        ("block", f"crc {blk.get('crc32') or '-'}, sequence {_or_dash(blk.get('sequence'))}, "
                  f"lead {_fmt(blk.get('lead_s'), 1e6)} us", ""),
        ("ECU boots", f"{ecu.get('block', '-')} block, sequence {_or_dash(ecu.get('sequence'))}", ""),
    ]
    table = "\n".join(f"<tr><th>{e(a)}</th><td>{e(b)}</td><td>{e(c)}</td></tr>" for a, b, c in rows)
    steps = "\n".join(f"<tr><td>{e(s['step'])}</td><td>{_fmt(s['seconds'], 1, 3)} s</td>"
                      f"<td>{'ok' if s['ok'] else ('writing this page' if s['seconds'] is None else 'FAILED')}</td></tr>"
                      for s in rec.get("steps", []))
    reasons = "".join(f"<li>{e(r)}</li>" for r in rec.get("reasons") or []) or "<li>all limits met</li>"
    imgs = "\n".join(f'<figure><img src="{e(f)}" alt="{e(c)}" style="max-width:100%"><figcaption>{e(c)}</figcaption></figure>'
                     for f, c in figures)
    files = [("report.json", "run record")] + [
        (Path(c["path"]).name, f"capture {k} (SHA-256 {c['sha256'][:16]}...)") for k, c in (rec.get("captures") or {}).items()
    ] + ([("fit.json", "fit result")] if rec.get("fit") else []) + ([("block.bin", "parameter block")] if blk else [])
    links = "".join(f'<li><a href="{e(f)}">{e(f)}</a>: {e(c)}</li>' for f, c in files)
    err = rec.get("error")
    err_html = (f"<p><b>error in step {e(err['step'])}</b>: {e(err['message'])}<br>safe state: "
                f"{e(str(rec.get('safe_state')))}</p>") if err else ""
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>eol-cal {e(rec['serial'])}: {e(v)}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:1em auto}} td,th{{padding:2px 10px;text-align:left}}
.v{{color:{colour};font-size:2em;font-weight:bold}}</style></head><body>
<h1>Motor {e(rec['serial'])} <span class="v">{e(v.upper())}</span></h1>
<p>variant {e(str(lim.get('variant')))} ({e(str(lim.get('source')))}), run {e(rec['run_id'])},
started {e(rec['started_at'])} (end time and total: report.json), eol-cal {e(str(rec.get('tool_version')))},
block layout {e(str(rec.get('layout_version')))}</p>
{err_html}<ul>{reasons}</ul>
<table>{table}</table>
{imgs}
<h2>Steps</h2><table>{steps}</table>
<h2>Files</h2><ul>{links}</ul>
</body></html>
"""


def write_report(rec: dict[str, Any], run_dir: str | Path, *, figures: list[tuple[str, str]] | None = None,
                 fit_extra: Any = None, point_ripple: Any = None) -> Path:
    """Write the plots and ``report.html`` into ``run_dir``; returns the HTML path.

    ``report.json`` is written by :func:`write_record_json` once the record is final.

    Parameters
    ----------
    rec : dict
        The run record (JSON-safe).
    run_dir : path
        The run's directory (exists).
    figures : list of (file name, caption), optional
        Plots already written (e.g. :func:`fit_plots` run while the dyno was busy).
    fit_extra : (MotorInput, MotorFit, FitSpec), optional
        For the fit plots, when not among ``figures``.
    point_ripple : (PointRipple, PointRipple), optional
        Before and compensated ripple at the operating point, for the ripple plot.
    """
    run_dir = Path(run_dir)
    figures = list(figures or [])
    if fit_extra is not None:
        figures += fit_plots(run_dir, fit_extra)
    if point_ripple is not None:
        figures += ripple_plot(run_dir, rec, point_ripple)
    html_path = run_dir / "report.html"
    _write_text(html_path, render_html(rec, figures))
    return html_path


def write_record_json(rec: dict[str, Any], run_dir: str | Path) -> Path:
    """``report.json``: the final run record, the same document the database holds."""
    path = Path(run_dir) / "report.json"
    _write_text(path, json.dumps(rec, indent=2, allow_nan=False) + "\n")
    return path


def plot_lot(path: str | Path, records: list[dict[str, Any]], title: str = "") -> None:
    """k6 and p-p ripple (before, compensated) of every run, in run order, into one PNG.

    Parameters
    ----------
    path : path
        PNG to write (atomically).
    records : list of dict
        Run records, oldest first.
    title : str
        Figure title.
    """
    import numpy as np

    from eol_cal.analysis.plots import _pyplot, _save

    plt = _pyplot()

    def values(get) -> np.ndarray:
        out = []
        for r in records:
            try:
                v = get(r)
            except (KeyError, TypeError):
                v = None
            out.append(np.nan if v is None else float(v))
        return np.array(out)

    n = np.arange(1, len(records) + 1)
    k6 = values(lambda r: r["fit"]["k6"]["value"]) * 1e3
    ci = values(lambda r: r["fit"]["k6"]["ci95"]) * 1e3
    before = values(lambda r: r["metrics"]["pp_before_pct"])
    after = values(lambda r: r["metrics"]["pp_after_pct"])
    verdicts = [r.get("verdict") for r in records]
    colours = np.array([{"pass": "tab:green", "fail": "tab:orange", "error": "tab:red"}.get(v, "k") for v in verdicts])
    fig, (ax_k, ax_p) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    try:
        ax_k.errorbar(n, k6, yerr=ci, fmt="none", ecolor="0.6", lw=1)
        ax_k.scatter(n, k6, c=colours, zorder=3, s=25)
        ax_k.set_ylabel("k6 (mN*m/A)")
        ax_k.grid(alpha=0.3)
        ax_p.plot(n, before, "o-", color="tab:blue", ms=4, lw=0.8, label="p-p before")
        ax_p.plot(n, after, "s-", color="tab:purple", ms=4, lw=0.8, label="p-p compensated")
        ax_p.scatter(n, np.where(np.isnan(after), before, after), c=colours, s=8, zorder=3)
        ax_p.set_ylabel("p-p ripple at the operating point (%)")
        ax_p.set_xlabel("run (oldest first); colour: green pass, orange fail, red error")
        ax_p.grid(alpha=0.3)
        ax_p.legend(fontsize=8)
        from matplotlib.ticker import MaxNLocator

        ax_p.xaxis.set_major_locator(MaxNLocator(integer=True))
        if 0 < len(records) <= 20:  # few runs: name them
            ax_p.set_xticks(n, [r["serial"] for r in records], rotation=30, ha="right", fontsize=7)
        n_pass = verdicts.count("pass")
        judged = n_pass + verdicts.count("fail")
        rate = f"{100 * n_pass / judged:.1f} %" if judged else "-"
        fig.suptitle(f"{title}: {len(records)} runs, pass rate {rate}")
        fig.tight_layout()
        _save(fig, path)
    finally:
        plt.close(fig)
