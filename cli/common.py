"""Helpers every command shares: error-to-exit-code mapping, JSON output, rich console."""

from __future__ import annotations

import functools
import json
import os
import sys
from typing import Any, Callable

import click
from rich.console import Console

from eol_cal.errors import EolCalError

#: width of tables written to a file or a pipe (a station log, CI) unless $COLUMNS says otherwise:
#: rich's default of 80 there cut the fit table's values to "0.61..."
LOG_WIDTH = 160


def _console(stderr: bool = False, file: Any = None) -> Console:
    c = Console(stderr=stderr, file=file)
    if not c.is_terminal and "COLUMNS" not in os.environ:
        c.width = LOG_WIDTH
    return c


console = _console()
err_console = _console(stderr=True)


def handle_errors(func: Callable) -> Callable:
    """Turn library errors into a one-line message on stderr and the documented exit code."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except EolCalError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(exc.exit_code)

    return wrapper


def print_json(obj: Any) -> None:
    """Machine output: one JSON document on stdout, keys as documented in docs/json.md."""
    click.echo(json.dumps(obj, indent=2, sort_keys=False, allow_nan=False))
