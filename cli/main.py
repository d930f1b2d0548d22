"""The ``eol-cal`` command group. Each command lives in its own module under ``cli/``."""

from __future__ import annotations

import click

from eol_cal import __version__


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="eol-cal")
def cli() -> None:
    """End-of-line torque-ripple calibration for EPS motors with a 64 PPR encoder.

    Exit codes: 0 ok, 1 a check or limit failed, 2 bad input or usage.
    """


def _register() -> None:
    # Each module adds its commands; heavy imports (JAX, CAN) stay inside the commands.
    import importlib

    for name in _COMMAND_MODULES:
        module = importlib.import_module(f"cli.{name}")
        for command in module.COMMANDS:
            cli.add_command(command)


# One line per command module; keep sorted.
_COMMAND_MODULES: list[str] = [
    "analyze",
    "block",
    "capture",
    "dyno",
    "ecu",
    "fit",
    "golden",
    "index",
    "lot",
    "msa",
    "operator",
    "refit",
    "restore",
    "simulate",
    "station",
    "table",
]

_register()


_ENDING_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")


def _ignore_signals() -> None:
    # the last atexit handler: past it Python resets its handlers to the default, and a signal
    # during the C-level teardown (XLA's threads) killed the process by the signal (exit -2)
    import signal

    for name in _ENDING_SIGNALS:
        signal.signal(getattr(signal, name), signal.SIG_IGN)


def _exit_at_once_on_a_signal() -> None:
    """From here on the outcome is decided and said: a signal (a second Ctrl-C while threads
    and atexit handlers finish) ends the process at once with exit 2, and during the teardown
    after the last atexit handler it is ignored; never the signal's own death (130)."""
    import contextlib
    import os
    import signal
    import sys

    def now(signum: int, frame: object) -> None:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):  # a closed pipe: nothing more can be said
                stream.flush()
        os._exit(2)

    for name in _ENDING_SIGNALS:
        signal.signal(getattr(signal, name), now)


def main() -> None:
    import atexit

    from eol_cal.blas import limit_blas_threads

    atexit.register(_ignore_signals)  # registered first: runs last
    limit_blas_threads()
    try:
        cli(prog_name="eol-cal")
    except KeyboardInterrupt:
        # Ctrl-C before a command set its handlers (imports, option parsing): one line, exit 2
        from eol_cal.errors import Interrupted

        click.echo(f"error: {Interrupted()}", err=True)
        raise SystemExit(Interrupted.exit_code) from None
    finally:
        _exit_at_once_on_a_signal()


if __name__ == "__main__":
    main()
