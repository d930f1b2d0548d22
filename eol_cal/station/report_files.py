"""Per-motor report: one self-contained HTML page, plus the run record as JSON.

Written into the run's own directory (next to its captures, fit and block), atomically (temp
file in the same directory, fsync, rename):

- ``report.html``: the page of :mod:`eol_cal.report.motor_page` (verdict, every limit, ECU state,
  plots as inline SVG); it needs no file beside it and no network, so it can be mailed and
  archived with the motor
- ``report.json``: the run record (the same document the database holds)
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from eol_cal.infra.atomic import atomic_write
from eol_cal.rendering.figures import save_png
from eol_cal.lot.lot_page import timeline_figure
from eol_cal.report.motor_page import (
    Figure,
    FitExtra,
    PointRipples,
    angle_figure,
    drawn,
    render_motor_report,
    residual_figure,
    spectrum_figure,
)

if TYPE_CHECKING:
    from eol_cal.records.record import RunRecord


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, text)


def fit_plots(run_dir: str | Path, fit_extra: FitExtra) -> list[Figure]:
    """The plots that need only the fit (the residual of every segment); run while the dyno
    spins for the compensated capture.

    Parameters
    ----------
    run_dir : path
        The run's directory (unused: the figures are inlined into the page).
    fit_extra : (MotorInput, MotorFit, FitSpec)
        The motor's fit inputs, its fit and the model.
    """
    return [drawn("residual", lambda: residual_figure(fit_extra))]


def write_report(rec: RunRecord, run_dir: str | Path, *, figures: Sequence[Figure] | None = None,
                 fit_extra: FitExtra | None = None, point_ripple: PointRipples | None = None) -> Path:
    """Write ``report.html`` into ``run_dir``; returns its path.

    ``report.json`` is written by :func:`write_record_json` once the record is final.

    Parameters
    ----------
    rec : RunRecord
        The run record.
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
    figures = list(figures or [])
    if fit_extra is not None and not any(f.name == "residual" for f in figures):
        figures += fit_plots(run_dir, fit_extra)
    if point_ripple is not None:
        figures = [drawn("angle", lambda: angle_figure(rec, point_ripple, fit_extra)),
                   drawn("spectrum", lambda: spectrum_figure(rec, point_ripple))] + figures
    html_path = Path(run_dir) / "report.html"
    _write_text(html_path, render_motor_report(rec, figures))
    return html_path


def write_record_json(rec: RunRecord, run_dir: str | Path) -> Path:
    """``report.json``: the final run record, the same document the database holds."""
    path = Path(run_dir) / "report.json"
    _write_text(path, json.dumps(rec.to_json(), indent=2, allow_nan=False) + "\n")
    return path


#: what a page rebuilt from its record says in place of its plots
REBUILT_NOTE = ("The page was rebuilt from the run record: the station ended before it had drawn it (the record "
                "was safe in the spool). The plots need the run's fit: eol-cal fit on the captures beside this page.")


def rebuild_missing(records: Sequence[RunRecord]) -> list[Path]:
    """The pages of runs whose station ended before it wrote them (a SIGKILL or a power cut while
    the report thread drew them), from their records: ``report.html`` without the plots (a note
    says why) and ``report.json``, each only where it is missing, atomically. Only in the run's own
    directory (a spooled record is a file anyone could have written: its ``report_dir`` must be a
    directory the station made for this run, named after its run id); one gone or that cannot be
    written is left as it is. Returns the pages written."""
    written: list[Path] = []
    for rec in records:
        run_dir = Path(rec.report_dir) if rec.report_dir else None
        if (run_dir is None or not run_dir.name.endswith(f"_{rec.run_id[:8]}") or run_dir.is_symlink()
                or not run_dir.is_dir()):
            continue
        try:
            if not (run_dir / "report.json").exists():
                write_record_json(rec, run_dir)
            html = run_dir / "report.html"
            if not html.exists():
                note = Figure("plots", "not drawn: the page was rebuilt from the record",
                              f'<p class="plot-error">{REBUILT_NOTE}</p>')
                _write_text(html, render_motor_report(rec, [note]))
                written.append(html)
        except Exception:  # noqa: BLE001 - one run's directory must not stop the others' (or the flush)
            continue
    return written


def plot_lot(path: str | Path, records: list[RunRecord], title: str = "") -> None:
    """k6 and p-p ripple (before, compensated) of every run against its start time, with the
    variants' limits and the error runs, into one PNG (:func:`eol_cal.lot.lot_page.timeline_figure`).

    Parameters
    ----------
    path : path
        PNG to write (atomically).
    records : list of RunRecord
        Run records.
    title : str
        Figure title.
    """
    save_png(timeline_figure(records, title), path)
