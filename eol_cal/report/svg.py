"""matplotlib figures as inline SVG: deterministic bytes, ids unique per page, hover titles.

Several SVG documents inlined in one HTML page share its id namespace; matplotlib names its
clip paths, glyphs and markers by content hashes, so two figures may define the same id with
different content. Every id of a figure is therefore prefixed with the figure's own name.
"""

from __future__ import annotations

import io
import re
from typing import Any, Sequence
from xml.sax.saxutils import escape

_ID = re.compile(r'\bid="([^"]+)"')
_REF = re.compile(r'(url\(#|href="#)([^")]+)')
#: what every SVG the reports inline is written with: fixed hash salt (clip path ids), glyphs as
#: paths (no font needed where the page is opened), no date in the metadata
RC = {"svg.hashsalt": "eol-cal", "svg.fonttype": "path", "svg.image_inline": True}


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (imported on first use: it costs a second)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_svg(fig: Any, name: str, titles: dict[str, Sequence[str]] | None = None) -> str:
    """The figure as an ``<svg>`` element for inlining into HTML; closes the figure.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure (artists whose points get hover titles carry a ``gid``).
    name : str
        Prefix of every id in the SVG: unique on the page (letters, digits, ``-``).
    titles : dict of gid -> list of str, optional
        Hover text per point of the artist with that ``gid`` (a scatter: one marker per point,
        in the order of the data), written as SVG ``<title>`` elements.

    Returns
    -------
    str
        ``<svg ...>...</svg>`` without the XML prolog, width 100 % of its container.
    """
    import matplotlib

    buf = io.StringIO()
    try:
        with matplotlib.rc_context(RC):
            # dpi: resolution of the rasterized parts (dense point clouds drawn as one embedded PNG
            # each, which keeps a page at a few hundred kB; axes, text and curves stay vectors)
            fig.savefig(buf, format="svg", dpi=150, metadata={"Date": None, "Creator": None})
    finally:
        pyplot().close(fig)
    text = buf.getvalue()
    text = text[text.index("<svg"):]
    if titles:
        text = _add_titles(text, titles)
    text = _ID.sub(lambda m: f'id="{name}-{m.group(1)}"', text)
    text = _REF.sub(lambda m: f"{m.group(1)}{name}-{m.group(2)}", text)
    # scale with the page (the viewBox keeps the aspect ratio); printing keeps it on the sheet
    text = re.sub(r'<svg([^>]*?) width="[^"]+" height="[^"]+"', r'<svg\1 class="plot" style="width:100%;height:auto"',
                  text, count=1)
    return text


def _add_titles(text: str, titles: dict[str, Sequence[str]]) -> str:
    """Put a ``<title>`` into each point of the groups named in ``titles``.

    matplotlib draws a scatter's points as ``<use>`` elements, in data order, in one clipped
    group inside ``<g id="gid">`` (non-finite points are not drawn: callers leave them out).
    """
    for gid, labels in titles.items():
        start = text.find(f'<g id="{gid}"')
        if start < 0:
            raise ValueError(f"no artist with gid {gid!r} in the figure")
        first = text.find("<use ", start)
        end = text.find("</g>", first) if first >= 0 else start
        it = iter(labels)

        def one(m: re.Match) -> str:
            label = next(it, None)
            return m.group(0) if label is None else m.group(0)[:-2] + f"><title>{escape(label)}</title></use>"

        text = text[:start] + re.sub(r"<use [^>]*?/>", one, text[start:end]) + text[end:]
    return text
