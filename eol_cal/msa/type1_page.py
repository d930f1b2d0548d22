"""The type-1 study's plots and page: per quantity a run chart (the measurements in run order
with the reference, the band ``x_ref -+ K T / 2`` and the mean) and a histogram; the page in the
style of the lot page (one self-contained HTML file) and the same figures as PNG files."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from eol_cal.infra.atomic import atomic_write
from eol_cal.rendering.figures import pyplot, save_png
from eol_cal.msa.study import quantity
from eol_cal.msa.type1 import CAPABLE, Type1Study
from eol_cal.report.motor_page import Figure
from eol_cal.report.html import render
from eol_cal.report.svg import figure_svg

if TYPE_CHECKING:
    from matplotlib.figure import Figure as MplFigure


def study_figure(st: Type1Study, title: str, run_titles: Sequence[str] = ()) -> tuple[MplFigure, dict[str, list[str]]]:
    """Run chart and histogram of one quantity's study (display units).

    Returns
    -------
    figure, titles
        The figure and the hover text of its points (gid ``values-KEY``). Lines with a gid:
        ``ref-KEY`` (reference), ``band-KEY`` (``x_ref -+ K T / 2``), ``mean-KEY``.
    """
    plt = pyplot()
    fig, (ax, ax_h) = plt.subplots(1, 2, figsize=(10, 2.9), gridspec_kw={"width_ratios": [3, 1]}, sharey=True)
    x = np.asarray(st.values, dtype=float)
    runs = np.arange(1, len(x) + 1)
    key = st.quantity
    ax.plot(runs, x, "-", color="0.6", lw=0.7)
    ax.scatter(runs, x, s=14, zorder=3, color="tab:blue", gid=f"values-{key}")
    if st.reference is not None:
        ax.axhline(st.reference, color="tab:green", lw=1.2, gid=f"ref-{key}", label=f"x_ref {st.reference:.4g}")
    band = st.band
    if band is not None:
        for i, b in enumerate(band):
            ax.axhline(b, color="tab:red", ls="--", lw=1.0, gid=f"band-{key}" if i == 0 else None,
                       label=f"x_ref -+ {st.k / 2:.0%} T" if i == 0 else None)
    if math.isfinite(st.mean):
        ax.axhline(st.mean, color="0.3", lw=0.8, ls=":", gid=f"mean-{key}", label=f"mean {st.mean:.4g}")
    ax.set_xlabel("run", fontsize=8)
    ax.set_ylabel(st.unit, fontsize=8)
    ax.set_title(f"{title}: {line(st)}", fontsize=8)
    ax.legend(fontsize=6, loc="upper left", ncol=3)
    finite = x[np.isfinite(x)]
    if len(finite):
        ax_h.hist(finite, bins=min(20, max(5, int(np.sqrt(len(finite))) + 1)), orientation="horizontal",
                  color="tab:blue", alpha=0.8)
    ax_h.set_xlabel("runs", fontsize=8)
    for a in (ax, ax_h):
        a.grid(alpha=0.3)
        a.tick_params(labelsize=7)
    fig.tight_layout()
    titles = {f"values-{key}": [f"{t}: {v:.5g} {st.unit}" for t, v in zip(run_titles, x, strict=True)]} if run_titles else {}
    return fig, titles


def line(st: Type1Study) -> str:
    """``n = 25, s = 0.0012, bias = 0.0003, Cg 3.06, Cgk 2.45`` (the reasons where not given)."""
    parts = [f"n = {st.n}"]
    if math.isfinite(st.sd):
        parts.append(f"s = {st.sd:.3g}")
    if math.isfinite(st.bias):
        parts.append(f"bias = {st.bias:.3g}")
    parts.append(f"Cg {st.cg.text()}")
    parts.append(f"Cgk {st.cgk.text()}")
    return ", ".join(parts)


def write_pngs(results: Sequence[tuple[Type1Study, str]], directory: str | Path) -> list[Path]:
    """One PNG per quantity, ``type1-KEY.png`` in ``directory`` (made when missing)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    out = []
    for st, _src in results:
        path = directory / f"type1-{st.quantity}.png"
        save_png(study_figure(st, quantity(st.quantity).title)[0], path)
        out.append(path)
    return out


def render_page(doc: dict[str, Any], results: Sequence[tuple[Type1Study, str]], *, title: str,
                run_titles: Sequence[str]) -> str:
    """The study's page (self-contained HTML): the verdict, the convention, a table of the
    figures (each index or the reason it is not given) and each quantity's run chart."""
    figures = []
    for st, _src in results:
        fig, titles = study_figure(st, quantity(st.quantity).title, run_titles)
        name = f"type1-{st.quantity.replace('_', '-')}"
        figures.append(Figure(name, f"{quantity(st.quantity).title}: the master's measurements in run order; "
                              "green the reference, red dashed the band x_ref -+ K T / 2 the measurements of a "
                              "capable gauge stay in, dotted the mean. Hover on a point: the run",
                              figure_svg(fig, name, titles, "plot zoom")))
    return render("msa.html.j2", title=title, doc=doc, figures=figures, capable_at=CAPABLE, fmt=_fmt)


def _fmt(x: float | None, digits: int = 4) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{float(x):.{digits}g}"


def write_page(path: str | Path, doc: dict[str, Any], results: Sequence[tuple[Type1Study, str]], *, title: str,
               run_titles: Sequence[str]) -> Path:
    """Write the study's page to ``path`` (atomically); returns the path."""
    path = Path(path)
    atomic_write(path, render_page(doc, results, title=title, run_titles=run_titles))
    return path
