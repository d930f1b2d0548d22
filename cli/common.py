"""Helpers every command shares: error-to-exit-code mapping, JSON output, rich console."""

from __future__ import annotations

import functools
import json
import sys
from typing import Any, Callable

import click
from rich.console import Console

from eol_cal.errors import EolCalError

console = Console()
err_console = Console(stderr=True)


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
