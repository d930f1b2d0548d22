"""matplotlib figures as inline SVG: deterministic bytes, ids unique per page, hover titles.

Several SVG documents inlined in one HTML page share its id namespace; matplotlib names its
clip paths, glyphs and markers by content hashes, so two figures may define the same id with
different content. Every id of a figure is therefore prefixed with the figure's own name.
"""

from __future__ import annotations

import io
import re
from typing import TYPE_CHECKING
from collections.abc import Iterator, Mapping, Sequence
from xml.sax.saxutils import escape

from eol_cal.rendering.figures import pyplot
from eol_cal.rendering.renderer import literal_texts

if TYPE_CHECKING:
    from matplotlib.figure import Figure as MplFigure
    from matplotlib.typing import RcKeyType

_ID = re.compile(r'\bid="([^"]+)"')
_REF = re.compile(r'(url\(#|href="#)([^")]+)')
#: what every SVG the reports inline is written with: fixed hash salt (clip path ids), glyphs as
#: paths (no font needed where the page is opened), no date in the metadata
RC: dict[RcKeyType, object] = {"svg.hashsalt": "eol-cal", "svg.fonttype": "path", "svg.image_inline": True}


def figure_svg(fig: MplFigure, name: str, titles: Mapping[str, Sequence[str]] | None = None, css_class: str = "plot") -> str:
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
    css_class : str
        The ``<svg>`` element's class (``plot``; ``plot zoom`` for the pages' zoom script).

    Returns
    -------
    str
        ``<svg ...>...</svg>`` without the XML prolog, width 100 % of its container.
    """
    import matplotlib

    buf = io.StringIO()
    literal_texts(fig)
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
    text = re.sub(r'<svg([^>]*?) width="[^"]+" height="[^"]+"', rf'<svg\1 class="{css_class}" style="width:100%;height:auto"',
                  text, count=1)
    return text


def _group_end(text: str, start: int) -> int:
    """Index just past the ``</g>`` that closes the ``<g`` opened at ``start``."""
    depth = 0
    for m in _G.finditer(text, start):
        if m.group(0) == "</g>":
            depth -= 1
            if depth == 0:
                return m.end()
        elif not m.group(0).endswith("/>"):
            depth += 1
        elif depth == 0:  # the group itself is empty (<g id=".."/>: a scatter without points)
            return m.end()
    return len(text)


_G = re.compile(r"<g\b[^>]*>|</g>")
_POINT = re.compile(r"<(use|path) [^>]*?/>")


def _add_titles(text: str, titles: Mapping[str, Sequence[str]]) -> str:
    """Put a ``<title>`` into each point of the groups named in ``titles``.

    matplotlib draws a scatter's points in data order inside ``<g id="gid">``: as ``<use>`` of
    a marker defined in the group's ``<defs>`` (one clipped group for all, or one per point when
    their colours differ), or, for a few points, each as its own ``<path>``. Non-finite points
    are not drawn: callers leave them out.
    """
    for gid, labels in titles.items():
        start = text.find(f'<g id="{gid}"')
        if start < 0:
            raise ValueError(f"no artist with gid {gid!r} in the figure")
        end = _group_end(text, start)
        # the points outside <defs>: <use> of a marker, or (few points) each its own <path>
        parts = re.split(r"(<defs>.*?</defs>)", text[start:end], flags=re.S)
        drawn = sum(len(_POINT.findall(p)) for p in parts[::2])
        if drawn != len(labels):  # a title on the wrong point would name the wrong motor
            raise ValueError(f"artist {gid!r}: {drawn} points drawn, {len(labels)} titles")
        it = iter(labels)

        def one(m: re.Match, it: Iterator[str] = it) -> str:  # bound here: called within this iteration
            return f"{m.group(0)[:-2]}><title>{escape(next(it))}</title></{m.group(1)}>"

        parts[::2] = [_POINT.sub(one, p) for p in parts[::2]]
        body = "".join(parts)
        text = text[:start] + body + text[end:]
    return text
