"""`eol-cal run`'s verdict line, printed as soon as the cycle knows it: plain text on a console that
takes no markup (a serial or a reason is printed as it is), the colour a style."""

from __future__ import annotations

import io
from types import SimpleNamespace

from rich.console import Console

import cli.station as station_cli


def test_the_verdict_line_is_text_not_markup(monkeypatch) -> None:
    buf = io.StringIO()
    monkeypatch.setattr(station_cli, "console", Console(file=buf, markup=False, emoji=False, force_terminal=True,
                                                        color_system="standard"))
    station_cli._print_verdict(SimpleNamespace(kind="production", verdict="fail", serial="M[/]-1",
                                               reasons=["max_pp_after_pct: 2.1 > 2.0 [%]"]))
    out = buf.getvalue()
    assert "[bold" not in out and "[/]" not in out.replace("M[/]-1", "")
    assert "M[/]-1: FAIL" in out and "(max_pp_after_pct: 2.1 > 2.0 [%])" in out
    assert "\x1b[" in out  # styled on a terminal (yellow for a fail)
