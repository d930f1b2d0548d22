"""Helpers every command shares: error-to-exit-code mapping, JSON output, rich console."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator

import click
from rich.console import Console

from eol_cal.errors import EolCalError, Interrupted

#: width of tables written to a file or a pipe (a station log, CI) unless $COLUMNS says otherwise:
#: rich's default of 80 there cut the fit table's values to "0.61..."
LOG_WIDTH = 160


def _console(stderr: bool = False, file: Any = None) -> Console:
    # no markup, no emoji codes: serials, file names and reasons are printed as they are ("[/]" in
    # a name was a MarkupError traceback); our own colours are rich.text.Text styles (styled())
    c = Console(stderr=stderr, file=file, markup=False, emoji=False)
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
    Ctrl-C. Inside ``eol_cal.infra.interrupts.shielded`` (a record being written) it waits for the end;
    inside a finalizer it comes again a moment later; a main thread stuck in a system call is
    ended by the watchdog (``eol_cal.infra.interrupts``). Outside the main thread (a test invoking the
    CLI from a worker) handlers cannot be set and nothing changes.
    """
    from eol_cal.infra import interrupts

    interrupts.reset()
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def raise_interrupted(signum: int, frame: Any) -> None:
        interrupts.deliver(signal.Signals(signum).name, frame)

    previous = {sig: signal.signal(sig, raise_interrupted) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        with interrupts.watchdog(), interrupts.dropped_redelivered():
            yield
    finally:
        interrupts.stop_redelivery()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def styled(*parts: str | tuple[str, str]) -> Any:
    """Console text from plain strings and ``(text, style)`` pairs; nothing in them is markup."""
    from rich.text import Text

    return Text.assemble(*parts)


def _option_hint(exc: EolCalError) -> str:
    """The command-line option that fixes an error the library reports in its own terms."""
    from eol_cal.capture.channel_map import ForeignChannelError

    return " (give one with --map FILE)" if isinstance(exc, ForeignChannelError) else ""


class CommandExit(Exception):
    """A command has printed its outcome itself and ends with ``exit_code`` (nothing more is printed).

    Commands raise this instead of calling :func:`sys.exit`, so that :func:`handle_errors` is the
    one place where an outcome becomes the process's exit status (0 ok, 1 a check failed, 2 bad input).
    """

    def __init__(self, exit_code: int) -> None:
        self.exit_code = exit_code
        super().__init__(f"exit code {exit_code}")


def handle_errors(func: Callable) -> Callable:
    """Map every way a command ends to its exit code: the one place the CLI calls :func:`sys.exit`.

    :class:`CommandExit` ends silently with its code; library errors (:class:`EolCalError`) and
    SIGINT/SIGTERM print a one-line message on stderr and end with the error's code.
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from eol_cal.infra import interrupts
        from eol_cal.infra.inputs import command_inputs

        try:
            with signals_interrupt(), command_inputs():
                result = func(*args, **kwargs)
                interrupts.raise_if_received()  # a signal whose exception a finalizer swallowed
        except CommandExit as exc:
            if exc.exit_code != Interrupted.exit_code and interrupts.received():
                click.echo(f"error: {Interrupted(interrupts.received())}", err=True)
                sys.exit(Interrupted.exit_code)
            if exc.exit_code:
                sys.exit(exc.exit_code)
            return None
        except EolCalError as exc:
            click.echo(f"error: {exc}{_option_hint(exc)}", err=True)
            sys.exit(exc.exit_code)
        except KeyboardInterrupt as exc:  # Interrupted, or Ctrl-C before the handlers were set
            click.echo(f"error: {exc if isinstance(exc, Interrupted) else Interrupted()}", err=True)
            sys.exit(Interrupted.exit_code)
        return result

    return wrapper


def print_json(obj: dict[str, Any]) -> None:
    """Machine output: one JSON document on stdout, keys as documented in docs/json.md; every
    document names its schema (``"schema": "eol-cal/NAME/VERSION"``, a file in eol_cal/schemas)."""
    if not isinstance(obj, dict) or not str(obj.get("schema", "")).startswith("eol-cal/"):
        raise TypeError("a --json document without its schema key")  # a programming error, not the user's
    click.echo(json.dumps(obj, indent=2, sort_keys=False, allow_nan=False))


def kind_option(what: str, default: str = "production") -> Callable:
    """``--kind KIND|all``: which run kinds (docs/records.md, "Run kinds") a command takes; ``what``
    ends its help."""
    from eol_cal.records.kinds import KINDS

    return click.option("--kind", default=default, show_default=True, type=click.Choice([*KINDS, "all"]),
                        help=f"Run kind: {', '.join(KINDS)}, or all; {what}")


class RecordsDb(click.ParamType):
    """A records database: a SQLite file path, or a ``postgresql://user@host:port/db`` URL (kept as text)."""

    name = "PATH|URL"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str | Path:
        from eol_cal.infra.address import records_db
        from eol_cal.errors import InputError

        try:  # the one check of a database address (settings and variables take the same)
            return records_db(value, "db")
        except InputError as exc:
            self.fail(exc.reason if exc.file is None else f"{exc.file}: {exc.reason}", param, ctx)


RECORDS_DB = RecordsDb()


def exchange_log_options(func: Callable) -> Callable:
    """``--verbose`` and ``--log-file FILE`` for every command that talks to the ECU or the dyno.

    Both write the timestamped UDS and Modbus exchanges (:mod:`eol_cal.infra.exchange_log`): ``--verbose``
    on stderr, ``--log-file`` appended to FILE. Put it below :func:`handle_errors`, so a log file that
    cannot be opened is one line and exit 2::

        @click.command("x")
        @handle_errors
        @exchange_log_options
        def x_cmd(...): ...
    """

    @click.option("--log-file", type=click.Path(dir_okay=False), default=None,
                  help="Append the timestamped UDS/Modbus exchanges to this file.")
    @click.option("--verbose", is_flag=True, help="Print the timestamped UDS/Modbus exchanges on stderr.")
    @functools.wraps(func)
    def wrapper(*args: Any, verbose: bool = False, log_file: str | None = None, **kwargs: Any) -> Any:
        from cli.paths import LOG_FILE, check_io
        from eol_cal.infra.exchange_log import exchange_logging

        if log_file is not None:
            check_io((), (log_file,))  # not a directory, FIFO or device
            ctx = click.get_current_context(silent=True)
            if ctx is not None:  # an output of the command: checked against its inputs (cli.paths)
                ctx.meta[LOG_FILE] = log_file
        with exchange_logging(sys.stderr if verbose else None, log_file):
            return func(*args, **kwargs)

    return wrapper


def estimator_option(what: str, default: str | None = "best") -> Callable:
    """The ``--estimator`` option (paper|best|NAMES|0xMASK, default ``default``) of the commands
    that choose the firmware estimator's options (contract flags bits 2-5); ``what`` ends its help."""
    return click.option(
        "--estimator", "estimator", default=default, show_default=default is not None, metavar="paper|best|NAMES|0xMASK",
        help="Estimator options (block flags bits 2-5): paper (none), best (all four), option names joined "
             "by '+' (clamp_to_next_edge, learn_grid_offset, accel_prediction, learn_pitch_errors) or a hex "
             f"mask of bits 2-5; {what}")


def estimator_bits(text: str) -> int:
    """The option bits of an ``--estimator`` value (bad input: exit 2 naming the option)."""
    from eol_cal.firmware.options import parse_options

    return parse_options(text, None, "--estimator")


def loop_kernels() -> None:
    """The tick loops of this process as single XLA loop kernels
    (:func:`eol_cal.numerics.xla.configure_xla`): the fit's firmware frame (the estimator's scan,
    ~10x less CPU, bit for bit the same: tests/test_firmware_frame_chunk.py) in `eol-cal fit`,
    `run` and `station`, and the built-in plant's where the process simulates it (`station --demo`,
    `demo`, `dyno-sim --source plant`: a demo motor ~40 % less CPU, within float32 rounding of XLA's
    defaults, the identification the same: tests/test_plant_identifying_loop.py), as `eol-cal
    simulate`, the lot simulation's workers and the tests run it. In the `eol-cal` process only: a
    command invoked by a test in the test's process (click's runner) leaves XLA's settings to it."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if os.path.basename(sys.argv[0]) != "eol-cal" and getattr(spec, "name", None) != "cli.main":
        return
    from eol_cal.numerics.xla import configure_xla

    configure_xla()  # before the process's first JAX computation
