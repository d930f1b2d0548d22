"""The lot: runs against time with their limits, and the lot page.

:func:`timeline_figure` is what ``eol-cal records --plot`` draws (k6 and the p-p ripple before
and compensated against the run's start time, each variant's limits as lines, failed runs
marked, runs that ended in an error as red lines at their time: they have no values but they
happened). The lot page (:func:`render_lot_page`) puts the lot's statistics around it.
"""

from __future__ import annotations

import datetime as dt
import math
from typing import Any, Callable, Sequence

import numpy as np

from eol_cal.report.svg import pyplot

VERDICT_COLOUR = {"pass": "tab:green", "fail": "tab:orange", "error": "tab:red"}


def run_time(rec: dict[str, Any]) -> dt.datetime:
    """The run's start as a naive UTC datetime (matplotlib's date axis)."""
    t = dt.datetime.fromisoformat(str(rec["started_at"]))
    if t.tzinfo is not None:
        t = t.astimezone(dt.timezone.utc).replace(tzinfo=None)
    return t


def value_of(rec: dict[str, Any], path: Sequence[str]) -> float:
    """A number in the record by its keys (NaN where the record has none)."""
    x: Any = rec
    for k in path:
        if not isinstance(x, dict) or x.get(k) is None:
            return math.nan
        x = x[k]
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _limit_steps(ax: Any, times: list[dt.datetime], recs: list[dict[str, Any]], key: str, scale: float,
                 colour: str, label: str) -> None:
    """A variant limit as a step line through the runs' times (a change of variant shows)."""
    lim = np.array([value_of(r, ("limits", key)) * scale for r in recs])
    if len(times) and np.isfinite(lim).any():
        ax.step(times, lim, where="post", color=colour, lw=1.0, ls="--", label=label, gid=f"limit-{key}")


def timeline_figure(records: list[dict[str, Any]], title: str = "") -> Any:
    """k6 and p-p ripple of every run against its start time, with the limits; error runs shown.

    Parameters
    ----------
    records : list of dict
        Run records (any order; drawn by time).
    title : str
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        Artists with a ``gid``: ``runs-k6``, ``runs-before``, ``runs-after`` (one marker per
        run that has the value), ``error-runs`` (one line per error run), ``limit-KEY``.
    """
    plt = pyplot()
    recs = sorted(records, key=run_time)
    times = [run_time(r) for r in recs]
    verdicts = [r.get("verdict") for r in recs]
    fig, (ax_k, ax_p) = plt.subplots(2, 1, figsize=(10, 6.0), sharex=True)
    k6 = np.array([value_of(r, ("fit", "k6", "value")) for r in recs]) * 1e3
    ci = np.array([value_of(r, ("fit", "k6", "ci95")) for r in recs]) * 1e3
    colours = [VERDICT_COLOUR.get(v, "k") for v in verdicts]
    ok = np.isfinite(k6)
    t_ok = [t for t, o in zip(times, ok) if o]
    ax_k.errorbar(t_ok, k6[ok], yerr=np.nan_to_num(ci[ok]), fmt="none", ecolor="0.6", lw=1)
    ax_k.scatter(t_ok, k6[ok], c=[c for c, o in zip(colours, ok) if o], s=22, zorder=3, gid="runs-k6",
                 label="k6 (green pass, orange fail)")
    _limit_steps(ax_k, times, recs, "max_k6", 1e3, "tab:red", "max_k6")
    ax_k.set_ylabel("k6 (mN*m/A)")
    for key, path, marker, colour in (("before", ("metrics", "pp_before_pct"), "o", "tab:blue"),
                                      ("after", ("metrics", "pp_after_pct"), "s", "tab:purple")):
        y = np.array([value_of(r, path) for r in recs])
        ok_y = np.isfinite(y)
        t_y = [t for t, o in zip(times, ok_y) if o]
        ax_p.plot(t_y, y[ok_y], "-", color=colour, lw=0.6, alpha=0.6)
        ax_p.scatter(t_y, y[ok_y], marker=marker, s=18, zorder=3, facecolor=colour,
                     edgecolor=[c for c, o in zip(colours, ok_y) if o], linewidth=1.2,
                     label=f"p-p {'before' if key == 'before' else 'compensated'}", gid=f"runs-{key}")
    _limit_steps(ax_p, times, recs, "max_pp_before_pct", 1.0, "tab:blue", "max_pp_before_pct")
    _limit_steps(ax_p, times, recs, "max_pp_after_pct", 1.0, "tab:purple", "max_pp_after_pct")
    ax_p.set_ylabel("p-p ripple at the operating point (%)")
    errors = [t for t, v in zip(times, verdicts) if v == "error"]
    for ax in (ax_k, ax_p):
        for i, t in enumerate(errors):
            ax.axvline(t, color="tab:red", lw=1.0, ls=":", gid="error-runs" if ax is ax_p else None,
                       label="error run (no values)" if (i == 0 and ax is ax_p) else None)
        ax.grid(alpha=0.3)
    ax_p.legend(fontsize=7, loc="upper left", ncol=3)
    ax_k.legend(fontsize=7, loc="upper left")
    ax_p.set_xlabel("run start (UTC); marker edge: green pass, orange fail")
    fig.autofmt_xdate()
    n = len(recs)
    counts = {v: verdicts.count(v) for v in ("pass", "fail", "error")}
    fig.suptitle(f"{title}: {n} runs, {counts['pass']} pass, {counts['fail']} fail, {counts['error']} error", fontsize=10)
    fig.tight_layout()
    return fig


def save_png(fig: Any, path: Any) -> None:
    """Write a figure as PNG (atomically) and close it."""
    from eol_cal.analysis.plots import _save

    try:
        _save(fig, path)
    finally:
        pyplot().close(fig)
