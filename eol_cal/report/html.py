"""Rendering the pages: one Jinja2 environment over the templates shipped with the package."""

from __future__ import annotations

import datetime as dt
import functools

import jinja2
from markupsafe import Markup


@functools.lru_cache(maxsize=1)
def environment() -> jinja2.Environment:
    """The templates in ``eol_cal/report/templates``, HTML-escaped unless marked safe."""
    env = jinja2.Environment(loader=jinja2.PackageLoader("eol_cal.report", "templates"),
                             autoescape=jinja2.select_autoescape(["html", "j2"]), undefined=jinja2.ChainableUndefined,
                             trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True)
    env.filters["svg"] = lambda text: Markup(text)  # our own matplotlib output, ids already prefixed
    env.filters["utc"] = utc_text
    return env


def utc_text(stamp: str | None) -> str:
    """``2026-11-23T21:58:03.919+00:00`` as ``2026-11-23 21:58:03 UTC`` (``-`` for none)."""
    if not stamp:
        return "-"
    try:
        t = dt.datetime.fromisoformat(str(stamp))
    except ValueError:
        return str(stamp)
    if t.tzinfo is not None:
        t = t.astimezone(dt.UTC)
    return t.strftime("%Y-%m-%d %H:%M:%S UTC")


def render(template: str, **context: object) -> str:
    """The page ``template`` rendered with ``context``."""
    return environment().get_template(template).render(**context)
