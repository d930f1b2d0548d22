"""The lot: runs against time with their limits, and the lot page.

:func:`timeline_figure` is what ``eol-cal records --plot`` draws (k6 and the p-p ripple before
and compensated against the run's start time, each variant's limits as lines, failed runs
marked, runs that ended in an error as red lines at their time: they have no values but they
happened). The lot page (:func:`render_lot_page`) puts the lot's statistics around it.
"""

from __future__ import annotations

import datetime as dt
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Sequence

import numpy as np

from eol_cal.rendering.display import display_unit
from eol_cal.lot.baseline import Baseline
from eol_cal.lot.runs import CHARTED, QUANTITIES, Lot, from_records
from eol_cal.lot.spc import CIRCULAR, DEFAULT_MIN_N, circular_histogram, circular_summary, natural_floor
from eol_cal.lot.spc_stats import CIRCLE_BINS, gated_text, quantity_note
from eol_cal.lot.summary import lot_summary
from eol_cal.rendering.figures import pyplot
from eol_cal.rendering.renderer import file_link, plain
from eol_cal.records.limits import limit_on
from eol_cal.records.record import MEASURED_KIND

if TYPE_CHECKING:
    from matplotlib.figure import Figure as MplFigure

    from eol_cal.records.record import RunRecord

VERDICT_COLOUR = {"pass": "tab:green", "fail": "tab:orange", "error": "tab:red"}
#: more points than this in one chart are drawn as an embedded image without hover text (each
#: SVG point with its title costs about 0.3 kB: 100 000 runs would make a 200 MB page)
MAX_HOVER_POINTS = 2000
#: stored unit of each lot quantity
_UNITS = {q.key: q.stored_unit for q in QUANTITIES}


def run_time(rec: RunRecord) -> dt.datetime:
    """The run's start as a naive UTC datetime (matplotlib's date axis)."""
    t = dt.datetime.fromisoformat(rec.started_at)
    if t.tzinfo is not None:
        t = t.astimezone(dt.UTC).replace(tzinfo=None)
    return t


def limit_of(rec: RunRecord, quantity: str) -> float:
    """The limit the run was judged against on ``quantity``, stored units (NaN: none)."""
    c = rec.check(quantity)
    return math.nan if c is None else c.limit


def _limit_steps(ax: Any, times: list[dt.datetime], recs: list[RunRecord], quantity: str, colour: str) -> None:
    """A variant limit as a step line through the runs' times (a change of variant shows)."""
    lim = np.array([limit_of(r, quantity) for r in recs]) * display_unit(_UNITS[quantity])[1]
    limit = limit_on(quantity)
    key = limit.key if limit else quantity
    if len(times) and np.isfinite(lim).any():
        ax.step(times, lim, where="post", color=colour, lw=1.0, ls="--", label=key, gid=f"limit-{key}")


def timeline_figure(records: list[RunRecord], title: str = "") -> MplFigure:
    """See :func:`timeline` (the figure alone)."""
    return timeline(records, title)[0]


def point_title(rec: RunRecord, text: str) -> str:
    """Hover text of a run's point: serial, verdict, time, the value."""
    return f"{rec.serial} ({rec.verdict}), {rec.started_at[:19].replace('T', ' ')}: {text}"


def _display(recs: Sequence[RunRecord], quantity: str) -> np.ndarray:
    """The runs' values of a lot quantity in its display unit (NaN where a run has none)."""
    return np.array([r.value(quantity) for r in recs], dtype=float) * display_unit(_UNITS[quantity])[1]


def timeline(records: list[RunRecord], title: str = "") -> tuple[MplFigure, dict[str, list[str]]]:
    """k6 and p-p ripple of every run against its start time, with the limits; error runs shown.

    Parameters
    ----------
    records : list of RunRecord
        Production run records (any order; drawn by time).
    title : str
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure, dict of gid -> list of str
        The figure, and the hover text of each point of its scatters. Artists with a ``gid``:
        ``runs-k6``, ``runs-before``, ``runs-after`` (one marker per run that has the value),
        ``error-runs`` (one line per error run), ``limit-KEY``.
    """
    plt = pyplot()
    recs = sorted(records, key=run_time)
    times = [run_time(r) for r in recs]
    verdicts = [r.verdict for r in recs]
    fig, (ax_k, ax_p) = plt.subplots(2, 1, figsize=(10, 6.0), sharex=True)
    k6 = _display(recs, "k6")
    ci = np.array([r.fit.estimates.k6.ci95 if r.fit is not None and r.fit.estimates is not None and
                   r.fit.estimates.k6.ci95 is not None else math.nan for r in recs]) * display_unit(_UNITS["k6"])[1]
    colours = [VERDICT_COLOUR.get(v, "k") for v in verdicts]
    ok = np.isfinite(k6)
    t_ok = [t for t, o in zip(times, ok, strict=True) if o]
    dense = len(recs) > MAX_HOVER_POINTS
    ax_k.errorbar(t_ok, k6[ok], yerr=np.nan_to_num(ci[ok]), fmt="none", ecolor="0.6", lw=1, rasterized=dense)
    ax_k.scatter(t_ok, k6[ok], c=[c for c, o in zip(colours, ok, strict=True) if o], s=22, zorder=3, gid="runs-k6",
                 rasterized=dense, label="k6 (green pass, orange fail)")
    _limit_steps(ax_k, times, recs, "k6", "tab:red")
    ax_k.set_ylabel(f"k6 ({display_unit(_UNITS['k6'])[0]})")
    for key, quantity, marker, colour in (("before", "pp_before_pct", "o", "tab:blue"),
                                          ("after", "pp_after_pct", "s", "tab:purple")):
        y = _display(recs, quantity)
        ok_y = np.isfinite(y)
        t_y = [t for t, o in zip(times, ok_y, strict=True) if o]
        ax_p.plot(t_y, y[ok_y], "-", color=colour, lw=0.6, alpha=0.6, rasterized=dense)
        ax_p.scatter(t_y, y[ok_y], marker=marker, s=18, zorder=3, facecolor=colour, rasterized=dense,
                     edgecolor=[c for c, o in zip(colours, ok_y, strict=True) if o], linewidth=1.2,
                     label=f"p-p {'before' if key == 'before' else 'compensated'}", gid=f"runs-{key}")
    _limit_steps(ax_p, times, recs, "pp_before_pct", "tab:blue")
    _limit_steps(ax_p, times, recs, "pp_after_pct", "tab:purple")
    ax_p.set_ylabel("p-p ripple at the operating point (%)")
    errors = [t for t, v in zip(times, verdicts, strict=True) if v == "error"]
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
    fig.suptitle(f"{plain(title)}: {n} runs, {counts['pass']} pass, {counts['fail']} fail, {counts['error']} error", fontsize=10)
    fig.tight_layout()
    if dense:
        return fig, {}
    titles = {"runs-k6": [point_title(r, f"k6 {v:.4g} {display_unit(_UNITS['k6'])[0]}")
                          for r, v in zip(recs, k6, strict=True) if math.isfinite(v)]}
    for key, quantity in (("before", "pp_before_pct"), ("after", "pp_after_pct")):
        titles[f"runs-{key}"] = [point_title(r, f"p-p {key} {v:.3g} %")
                                 for r, v in zip(recs, _display(recs, quantity), strict=True) if math.isfinite(v)]
    return fig, titles


# --------------------------------------------------------------------------- the lot page

def histogram_figure(lot: Lot, notes: dict[str, str] | None = None) -> MplFigure:
    """Histograms of :data:`QUANTITIES` over the runs that have them, with the limits.

    Parameters
    ----------
    lot : Lot
        The runs column-wise (:func:`eol_cal.lot.runs.from_records`).
    notes : dict of quantity key -> str, optional
        A line under each panel's title (the capability figures).
    """
    plt = pyplot()
    cols = 3
    rows = -(-len(QUANTITIES) // cols)
    fig = plt.figure(figsize=(10, 2.6 * rows))
    for k, q in enumerate(QUANTITIES):
        circular = q.key in CIRCULAR
        ax = fig.add_subplot(rows, cols, k + 1, projection="polar" if circular else None)
        x = lot.display(q)
        x = x[np.isfinite(x)]
        ax.set_gid(f"hist-{q.key}")
        if circular:
            _circle_histogram(ax, lot.values[q.key])
        elif len(x):
            ax.hist(x, bins=min(30, max(5, int(np.sqrt(len(x))) + 1)), color="tab:blue", alpha=0.8)
        for i, v in enumerate(lot.limit_values(q)):
            ax.axvline(v, color="tab:red", ls="--", lw=1.2, label=q.limit_key if i == 0 else None)
        if q.limit_key and ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6, loc="upper right")
        note = (notes or {}).get(q.key)
        ax.set_title(f"{q.title}: n = {len(x)}" + (f"\n{plain(note)}" if note else ""), fontsize=8)
        if not circular:
            ax.set_xlabel(q.unit, fontsize=7)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def _circle_histogram(ax: Any, theta: np.ndarray) -> None:
    """A phase (rad) as sectors on the circle with its circular mean as a line of length R."""
    counts, edges = circular_histogram(theta, CIRCLE_BINS)
    ax.bar(edges[:-1], counts, width=np.diff(edges), align="edge", color="tab:blue", alpha=0.8, edgecolor="white", lw=0.5)
    s = circular_summary(theta)
    if math.isfinite(s.mean) and counts.max() > 0:
        ax.plot([s.mean, s.mean], [0, s.resultant * counts.max()], color="tab:red", lw=1.6, gid="circular-mean")
    ax.set_yticklabels([])


def control_figure(records: Sequence[RunRecord], station: str,
                   limits: dict[str, dict[str, float]] | None = None, min_n: int = DEFAULT_MIN_N,
                   marks: dict[str, dict[str, str]] | None = None) -> tuple[MplFigure, dict[str, list[str]]]:
    """Individuals and moving-range charts of :data:`CHARTED` by run order (one step a run: runs
    seconds apart do not stack up), for one station, with the centre line, the 3-sigma limits and
    the 1- and 2-sigma zone lines of Nelson's rules 5 and 6 (an amplitude's LCL held at zero).

    Parameters
    ----------
    records : sequence of RunRecord
        The station's production runs.
    station : str
        Its name (titles, gids).
    limits : dict of quantity key -> {"center", "ucl", "lcl", "mr_center", "mr_ucl"}, optional
        Control limits (display units: a frozen baseline's) to draw instead of the station's own
        (:func:`eol_cal.lot.stats.imr_limits` of the points drawn, only with ``min_n`` of them;
        points beyond them are ringed).
    min_n : int
        Fewest points that give the station's own limits.
    marks : dict of quantity key -> {run id: text}, optional
        Runs to ring as breaking a run rule (gid ``rule-KEY``), with the rule as hover text.

    Returns
    -------
    figure, titles
        As :func:`timeline`; the points' gids are ``i-KEY`` and ``mr-KEY``.
    """
    from matplotlib.ticker import MaxNLocator

    plt = pyplot()
    recs = sorted(records, key=run_time)
    fig, axes = plt.subplots(2, len(CHARTED), figsize=(10, 4.4), sharex=True, squeeze=False)
    titles: dict[str, list[str]] = {}
    q = {x.key: x for x in QUANTITIES}
    for col, key in enumerate(CHARTED):
        title, unit = q[key].title, q[key].unit
        pts = [(k + 1, v, r) for k, (r, v) in enumerate(zip(recs, _display(recs, key), strict=True))]
        pts = [p for p in pts if math.isfinite(p[1])]
        t = [p[0] for p in pts]
        x = np.array([p[1] for p in pts])
        ax_i, ax_m = axes[0][col], axes[1][col]
        dense = len(pts) > MAX_HOVER_POINTS
        ax_i.plot(t, x, "-", color="0.6", lw=0.7, rasterized=dense)
        ax_i.scatter(t, x, s=14, zorder=3, c=[VERDICT_COLOUR.get(p[2].verdict, "k") for p in pts], gid=f"i-{key}",
                     rasterized=dense)
        if not dense:
            titles[f"i-{key}"] = [point_title(p[2], f"{title} {p[1]:.4g} {unit}") for p in pts]
        mr = np.abs(np.diff(x))
        if len(mr):
            ax_m.plot(t[1:], mr, "-", color="0.6", lw=0.7, rasterized=dense)
            ax_m.scatter(t[1:], mr, s=10, zorder=3, color="tab:blue", gid=f"mr-{key}", rasterized=dense)
            if not dense:
                titles[f"mr-{key}"] = [point_title(p[2], f"moving range {m:.3g} {unit}")
                                       for p, m in zip(pts[1:], mr, strict=True)]
        lim = (limits or {}).get(key)
        if lim is None and len(x) >= max(2, min_n):
            from eol_cal.lot.stats import imr_limits

            cl = imr_limits(x)
            floor = natural_floor(key)
            lim = {"center": cl.center, "ucl": cl.ucl, "lcl": cl.lcl if floor is None else max(floor, cl.lcl),
                   "mr_center": cl.mr_center, "mr_ucl": cl.mr_ucl}
            beyond = cl.beyond(x)
            if beyond:
                ax_i.scatter([t[i] for i in beyond], x[beyond], s=70, facecolor="none", edgecolor="tab:red", lw=1.4,
                             zorder=4, gid=f"beyond-{key}")
                titles[f"beyond-{key}"] = [point_title(pts[i][2], f"{title} {x[i]:.4g} {unit}: beyond the control limits")
                                           for i in beyond]
        ringed = [(i, (marks or {}).get(key, {}).get(p[2].run_id)) for i, p in enumerate(pts)]
        ringed = [(i, text) for i, text in ringed if text]
        if ringed:
            ax_i.scatter([t[i] for i, _ in ringed], x[[i for i, _ in ringed]], s=110, facecolor="none",
                         edgecolor="tab:purple", lw=1.6, zorder=5, gid=f"rule-{key}")
            titles[f"rule-{key}"] = [point_title(pts[i][2], f"{title} {x[i]:.4g} {unit}: {text}") for i, text in ringed]
        if not lim and len(x) < min_n:
            ax_i.text(0.01, 0.97, f"no control limits: n = {len(x)} < {min_n}", transform=ax_i.transAxes, va="top",
                      fontsize=7, color="0.3", gid=f"few-{key}")
        if lim:
            _zones(ax_i, key, lim, natural_floor(key))
            for ax, names in ((ax_i, ("center", "ucl", "lcl")), (ax_m, ("mr_center", "mr_ucl"))):
                for name in names:
                    v = lim.get(name)
                    if v is not None and math.isfinite(v):
                        ax.axhline(v, color="tab:red" if name != "center" and name != "mr_center" else "0.3",
                                   ls="--" if "cl" in name and "center" not in name else "-", lw=1.0,
                                   gid=f"cl-{key}-{name}")
        ax_i.set_title(f"{plain(station)}: {title} ({unit}), individuals", fontsize=8)
        ax_m.set_title("moving range", fontsize=8)
        ax_m.set_xlabel("run (the station's, in time order)", fontsize=7)
        for ax in (ax_i, ax_m):
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    fig.tight_layout()
    return fig, titles


def _zones(ax: Any, key: str, lim: dict[str, float], floor: float | None) -> None:
    """The 1- and 2-sigma zone lines (sigma = (UCL - centre) / 3) the quantity can take; an LCL
    held at the natural zero is labelled so."""
    center, ucl = lim.get("center"), lim.get("ucl")
    if center is None or ucl is None or not (math.isfinite(center) and math.isfinite(ucl)):
        return
    sigma = (ucl - center) / 3.0
    for k, side in ((1, 1), (1, -1), (2, 1), (2, -1)):
        if floor is None or center + side * k * sigma >= floor:
            ax.axhline(center + side * k * sigma, color="0.55", ls=":", lw=0.8, gid=f"zone-{key}-{k}{'+-'[side < 0]}")
    if floor is not None and center - 3.0 * sigma < floor:
        ax.text(0.01, 0.03, "LCL at the natural zero (centre - 3 sigma < 0)", transform=ax.transAxes, fontsize=6,
                color="tab:red", gid=f"lcl-floor-{key}")


def pareto_figure(causes: Sequence[tuple[str, int, float]]) -> MplFigure:
    """Failure causes as bars of runs (a run counted once per cause), most first, with the
    cumulative share of the runs as a line (:func:`eol_cal.lot.stats.pareto_of`)."""
    from matplotlib.ticker import MaxNLocator

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 0.9 + 0.32 * max(1, len(causes))))
    names = [plain(c) for c, _n, _s in causes][::-1]
    counts = [n for _c, n, _s in causes][::-1]
    ax.barh(names, counts, color=["tab:red" if c.startswith("error") else "tab:orange" for c in names], gid="pareto-bars")
    ax.set_xlabel("runs", fontsize=8)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # runs are whole
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3, axis="x")
    cum = ax.twiny()
    cum.plot([100 * s for _c, _n, s in causes][::-1], names, "o-", color="0.3", ms=3, lw=1)
    cum.set_xlim(0, 105)
    cum.set_xlabel("cumulative share of the runs (%)", fontsize=8)
    cum.tick_params(labelsize=7)
    fig.tight_layout()
    return fig


def worst_motors(records: Sequence[RunRecord], page_dir: str | Path, n: int = 15) -> list[dict[str, Any]]:
    """The motors nearest their limits (each serial's latest production run): errors and fails
    first, then by the smallest margin as a fraction of its limit (the record's checks, display units).

    Returns
    -------
    list of dict
        ``serial``, ``verdict``, ``started_at``, ``station``, ``key``, ``value``, ``limit``,
        ``margin``, ``unit``, ``reasons``, ``link`` (the run's report relative to ``page_dir``
        when that file exists, else None).
    """
    from eol_cal.report.motor_page import limit_rows
    from eol_cal.records.query import latest_per_serial

    order = {"error": 0, "fail": 1, "pass": 2}
    rows: list[dict[str, Any]] = []  # the function's rows
    for r in latest_per_serial(records).values():
        worst, rel = None, math.inf
        for row in limit_rows(r):
            if math.isfinite(row.margin) and row.limit != 0 and row.margin / abs(row.limit) < rel:
                worst, rel = row, row.margin / abs(row.limit)
        link = file_link(Path(str(r.report_dir)) / "report.html", page_dir) if r.report_dir else None
        rows.append({"serial": r.serial, "verdict": r.verdict, "started_at": r.started_at,
                     "station": r.station_label, "key": worst.key if worst else None,
                     "value": worst.value if worst else math.nan, "limit": worst.limit if worst else math.nan,
                     "margin": worst.margin if worst else math.nan, "unit": worst.unit if worst else "",
                     "reasons": list(r.reasons), "link": link, "_sort": (order.get(r.verdict, 3), rel)})
    rows.sort(key=lambda x: x["_sort"])
    return rows[:n]


def _safe_id(text: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in text).strip("-") or "x"


def render_lot_page(records: Sequence[RunRecord], page_dir: str | Path, *, title: str,
                    filters: dict[str, str | None], min_n: int = DEFAULT_MIN_N, baseline: Baseline | None = None,
                    kind: str = MEASURED_KIND) -> str:
    """The lot page (self-contained HTML) of a set of run records.

    The statistics, charts and the motors nearest their limits are of the runs of ``kind``
    (``production``; ``simulated`` for a what-if lot, ``all`` for every kind but refusals); the
    refusals (nothing written, nothing measured) are counted and shown with their own Pareto;
    runs of other kinds (restores, master runs...) are counted.

    Parameters
    ----------
    records : sequence of RunRecord
        The lot's run records (already filtered), any kind.
    page_dir : path
        The directory the page is written to (links to the per-motor reports are relative to it).
    title : str
        Page title (the database, say).
    filters : dict
        The filters that selected the lot, shown on the page (None: not filtered).
    min_n : int
        Fewest values that give a capability index or control limits (fewer: ``n = 7 < 25``).
    baseline : Baseline, optional
        Frozen control lines: the charts draw them and the runs are judged against them
        (Nelson's rules 1, 2, 3, 5, 6, listed and ringed).
    """
    from eol_cal.lot.stats import pareto_of
    from eol_cal.report.motor_page import Figure
    from eol_cal.report.html import render
    from eol_cal.report.svg import figure_svg
    from eol_cal.records.query import summarise

    ordered = sorted(records, key=lambda r: (run_time(r), r.run_id))
    recs = [r for r in ordered if (r.kind != "refusal" if kind == "all" else r.kind == kind)]
    refusals = [r for r in ordered if r.kind == "refusal"]
    lot = from_records(recs)
    summary = summarise(ordered, kind)
    doc = lot_summary(lot, None, min_n, baseline)
    causes = pareto_of(lot.causes)
    refused = pareto_of(r.causes() for r in refusals)
    figures: list[Figure] = []
    if recs:
        fig, titles = timeline(recs, title)
        figures.append(Figure("timeline", "k6 and p-p ripple of every run against its start time, with the limits; "
                              "error runs as red dotted lines. "
                              + ("Hover on a point: serial, verdict, time, value; " if titles else
                                 f"More than {MAX_HOVER_POINTS} runs: points without hover text; ")
                              + "wheel: zoom, drag: pan, double-click: back", figure_svg(fig, "timeline", titles, "plot zoom")))
        notes = {q["key"]: quantity_note(q) for q in doc["quantities"] if q["count"]}
        figures.append(Figure("histograms", "Distribution of the measured quantities over the runs that have them, "
                              "with the variant's limits; the phases on the circle (sectors of 15 deg, the red line: "
                              "circular mean, its length R). Cpk (sigma from the moving range) and Ppk (overall sd) "
                              f"of a one-variant lot, given from n = {min_n} on",
                              figure_svg(histogram_figure(lot, notes), "histograms")))
    pareto_fig = None
    if causes:
        pareto_fig = Figure("pareto", "Why runs did not pass: each limit a failed run's checks name, and the step "
                            "an error run ended in", figure_svg(pareto_figure(causes), "pareto"))
    refusal_fig = None
    if refused:
        refusal_fig = Figure("refusals", "Why runs were refused before anything was written to the ECU (refusal "
                             "codes): not results of the motors", figure_svg(pareto_figure(refused), "refusals"))
    stations: dict[str, list[RunRecord]] = {}
    for r in recs:
        stations.setdefault(r.station_label, []).append(r)
    control = [_control(name, runs, doc, baseline, min_n) for name, runs in sorted(stations.items())]
    dates = [r.started_at[:19].replace("T", " ") for r in ordered]
    return render("lot.html.j2", title=title, summary=summary, figures=figures, control=control,
                  fpy=doc["first_pass_yield"], doc=doc, causes=causes, pareto=pareto_fig, refused=refused,
                  refusal_fig=refusal_fig, refusal_runs=len(refusals), worst=worst_motors(recs, page_dir),
                  filters=filters, first=dates[0] if dates else "-", last=dates[-1] if dates else "-",
                  stations=sorted(stations), fmt=_fmt, gated=gated_text)


def _control(name: str, runs: list[RunRecord], doc: dict[str, Any], baseline: Baseline | None, min_n: int) -> Any:
    """One station's control charts: against the baseline's lines of its variant when there is
    one (the runs breaking a rule ringed), else its own limits from ``min_n`` runs on."""
    from eol_cal.report.motor_page import Figure
    from eol_cal.report.svg import figure_svg

    limits = None
    how = (f"by run order: centre line and control limits (mean +- 2.66 MRbar, MR: 3.267 MRbar; dotted: the 1- and "
           f"2-sigma zones) of the station's own runs from n = {min_n} on, points beyond them ringed red")
    if baseline is not None:
        lines = {j["quantity"]: j for j in doc["judged"] if j["station"] == name and j["reason"] is None}
        variants = {j["variant"] for j in doc["judged"] if j["station"] == name}
        if len(variants) == 1 and lines:
            limits = {k: {f: j[f] for f in ("center", "ucl", "lcl", "mr_center", "mr_ucl")} for k, j in lines.items()}
            how = (f"by run order: frozen centre line and limits (centre +- 3 sigma; dotted: the 1- and 2-sigma zones) "
                   f"of baseline {baseline.name!r}; runs that break one of Nelson's rules ringed purple (hover: the rule)")
        else:
            how = (f"baseline {baseline.name!r} has no lines for this station's variant(s) {', '.join(sorted(variants))}; "
                   + how)
    marks: dict[str, dict[str, str]] = {}
    for v in doc["violations"]:
        if v["station"] == name:
            for rid in v["runs"]:
                old = marks.setdefault(v["quantity"], {}).get(rid)
                marks[v["quantity"]][rid] = f"{old}; {v['text']}" if old else v["text"]
    fig, titles = control_figure(runs, name, limits, min_n, marks)
    fid = f"control-{_safe_id(name)}"
    return Figure(fid, f"Station {name}: individuals and moving range of k6 and the compensated p-p, {len(runs)} runs; "
                  + how, figure_svg(fig, fid, titles, "plot zoom"))


def _fmt(x: float | None, digits: int = 4) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{float(x):.{digits}g}"


def select_records(records: Sequence[RunRecord], variant: str | None = None, since: dt.date | None = None,
                   until: dt.date | None = None, station: str | None = None) -> list[RunRecord]:
    """The records of one variant, station and UTC day range (``until`` inclusive)."""
    return [r for r in records if (variant is None or (r.limits is not None and r.limits.variant == variant))
            and (station is None or r.station_label == station) and (since is None or run_time(r).date() >= since)
            and (until is None or run_time(r).date() <= until)]


def write_lot_page(records: Sequence[RunRecord], path: str | Path, *, title: str,
                   filters: dict[str, str | None], min_n: int = DEFAULT_MIN_N, baseline: Baseline | None = None,
                   kind: str = MEASURED_KIND) -> Path:
    """Write the lot page to ``path`` (atomically); returns the path. ``min_n``, ``baseline``,
    ``kind``: as :func:`render_lot_page`."""

    from eol_cal.infra.atomic import atomic_write

    path = Path(path)
    atomic_write(path, render_lot_page(records, path.parent, title=title, filters=filters, min_n=min_n,
                                       baseline=baseline, kind=kind))
    return path
