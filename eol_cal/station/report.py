"""Per-motor report: one self-contained HTML page, plus the run record as JSON.

Written into the run's own directory (next to its captures, fit and block), atomically (temp
file in the same directory, fsync, rename):

- ``report.html``: the page of :mod:`eol_cal.report.motor` (verdict, every limit, ECU state,
  plots as inline SVG); it needs no file beside it and no network, so it can be mailed and
  archived with the motor
- ``report.json``: the run record (the same document the database holds)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

from eol_cal.atomic import atomic_write
from eol_cal.report.motor import Figure


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, text)


def fit_plots(run_dir: str | Path, fit_extra: Any) -> list[Figure]:
    """The plots that need only the fit (the residual of every segment); run while the dyno
    spins for the compensated capture.

    Parameters
    ----------
    run_dir : path
        The run's directory (unused: the figures are inlined into the page).
    fit_extra : (MotorInput, MotorFit, FitSpec)
        The motor's fit inputs, its fit and the model.
    """
    from eol_cal.report.motor import residual_figure

    return [residual_figure(fit_extra)]


def write_report(rec: dict[str, Any], run_dir: str | Path, *, figures: Sequence[Figure] | None = None,
                 fit_extra: Any = None, point_ripple: Any = None) -> Path:
    """Write ``report.html`` into ``run_dir``; returns its path.

    ``report.json`` is written by :func:`write_record_json` once the record is final.

    Parameters
    ----------
    rec : dict
        The run record (JSON-safe).
    run_dir : path
        The run's directory (exists).
    figures : list of Figure, optional
        Figures already drawn (:func:`fit_plots`, run while the dyno was busy).
    fit_extra : (MotorInput, MotorFit, FitSpec), optional
        The fit: its residual figure when not among ``figures``, and the fitted ripple over the
        torque against angle.
    point_ripple : (PointRipple, PointRipple), optional
        Before and compensated ripple at the operating point (torque against angle, spectra).
    """
    from eol_cal.report.motor import angle_figure, render_motor_report, spectrum_figure

    figures = list(figures or [])
    if fit_extra is not None and not any(f.name == "residual" for f in figures):
        figures += fit_plots(run_dir, fit_extra)
    if point_ripple is not None:
        figures = [angle_figure(rec, point_ripple, fit_extra), spectrum_figure(rec, point_ripple)] + figures
    html_path = Path(run_dir) / "report.html"
    _write_text(html_path, render_motor_report(rec, figures))
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
