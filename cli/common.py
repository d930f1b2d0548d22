"""Helpers every command shares: error-to-exit-code mapping, JSON output, rich console."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import signal
import sys
import threading
from typing import Any, Callable, Iterator

import click
from rich.console import Console

from eol_cal.errors import EolCalError, Interrupted

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


@contextlib.contextmanager
def signals_interrupt() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP raise :class:`Interrupted` in the main thread while the command runs.

    SIGTERM's (and a closed terminal's SIGHUP's) default ends the process without cleanup (no
    safe state, no record); raised as an exception it unwinds through every ``finally`` like
    Ctrl-C. Inside ``eol_cal.interrupts.shielded`` (a record being written) it waits for the end. Outside the main thread
    (a test invoking the CLI from a worker) handlers cannot be set and nothing changes.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    from eol_cal.interrupts import deliver

    def raise_interrupted(signum: int, frame: Any) -> None:
        deliver(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, raise_interrupted) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _option_hint(exc: EolCalError) -> str:
    """The command-line option that fixes an error the library reports in its own terms."""
    from eol_cal.capture.channel_map import ForeignChannelError

    return " (give one with --map FILE)" if isinstance(exc, ForeignChannelError) else ""


def handle_errors(func: Callable) -> Callable:
    """Turn library errors and SIGINT/SIGTERM into a one-line message on stderr and the exit code."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with signals_interrupt():
                return func(*args, **kwargs)
        except EolCalError as exc:
            click.echo(f"error: {exc}{_option_hint(exc)}", err=True)
            sys.exit(exc.exit_code)
        except KeyboardInterrupt as exc:  # Interrupted, or Ctrl-C before the handlers were set
            click.echo(f"error: {exc if isinstance(exc, Interrupted) else Interrupted()}", err=True)
            sys.exit(Interrupted.exit_code)

    return wrapper


def print_json(obj: Any) -> None:
    """Machine output: one JSON document on stdout, keys as documented in docs/json.md."""
    click.echo(json.dumps(obj, indent=2, sort_keys=False, allow_nan=False))
