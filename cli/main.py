"""The ``eol-cal`` command group. Each command lives in its own module under ``cli/``."""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Iterable, Sequence


def _is_the_program() -> bool:
    """Whether this process is the eol-cal program (``eol-cal ...`` or ``python -m cli.main``), not
    a test importing the CLI nor a worker process that multiprocessing started from it."""
    main_file = os.path.basename(getattr(sys.modules.get("__main__"), "__file__", None) or "")
    if __name__ != "__main__" and main_file != "eol-cal":
        return False
    mp = sys.modules.get("multiprocessing")
    return mp is None or mp.parent_process() is None


def _end_while_starting(signum: int, frame: object) -> None:
    # nothing has been done yet (imports, option parsing): one line and exit 2, as for every
    # signal later; the command's own handlers (cli.common.signals_interrupt) replace this one
    os.write(2, f"error: interrupted by {signal.Signals(signum).name} while starting; nothing was done\n".encode())
    os._exit(2)


if _is_the_program():  # the first instruction: from here on a signal ends the program with exit 2, never 143/129/130
    for _name in ("SIGINT", "SIGTERM", "SIGHUP"):
        signal.signal(getattr(signal, _name), _end_while_starting)

import click  # noqa: E402 - after the signal handlers

from eol_cal import __version__  # noqa: E402


class _Commands(click.Group):
    """The command group, each command module imported when its command is asked for: ``eol-cal
    capture info`` loads ``cli/capture.py`` alone (the other modules bring numpy, the records'
    tables, ...); ``eol-cal --help`` lists them all and so imports them all."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        _load(_COMMAND_MODULES)
        return super().list_commands(ctx)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        # every module of the name, even when the command is there already: ``flash`` brought
        # cli/ecu.py's ``ecu`` group, whose ``restore`` cli/restore.py adds
        _load(modules_of(cmd_name))
        return super().get_command(ctx, cmd_name)


@click.group(cls=_Commands, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="eol-cal")
def cli() -> None:
    """End-of-line torque-ripple calibration for EPS motors with a 64 PPR encoder.

    Exit codes: 0 ok, 1 a check or limit failed, 2 bad input or usage.
    """


_LOADED: set[str] = set()


def modules_of(name: str) -> Sequence[str]:
    """The command modules that build command ``name``: :data:`_COMMAND_HOME`'s, else the module
    of its name; every module for a name of none (an unknown name then gets click's error)."""
    if name in _COMMAND_HOME:
        return _COMMAND_HOME[name]
    return (name,) if name in _COMMAND_MODULES else _COMMAND_MODULES


def _load(names: Iterable[str]) -> None:
    """Import the command modules ``names`` (once) and add their commands to the group; heavy
    imports (JAX, CAN) stay inside the commands."""
    import importlib

    for name in names:
        if name in _LOADED:
            continue
        _LOADED.add(name)
        module = importlib.import_module(f"cli.{name}")
        for command in module.COMMANDS:
            cli.add_command(command)


# One line per command module; keep sorted. A command is looked for in the module of its own name
# unless _COMMAND_HOME names others.
_COMMAND_MODULES: list[str] = [
    "analyze",
    "bench",
    "block",
    "capture",
    "dyno",
    "ecu",
    "fit",
    "gate",
    "golden",
    "index",
    "lot",
    "msa",
    "operator",
    "panel",
    "records",
    "refit",
    "restore",
    "simulate",
    "station",
    "table",
]

#: command -> the modules that build it, where that is not (only) the module of its name: the
#: command lives elsewhere, or another module adds subcommands to its group
#: (tests/test_cli_startup.py checks this against the commands of every module)
_COMMAND_HOME: dict[str, tuple[str, ...]] = {
    "acquire": ("dyno",),
    "demo": ("station",),
    "dyno-clear": ("dyno",),
    "dyno-sim": ("dyno",),
    "ecu": ("ecu", "restore"),
    "ecu-sim": ("ecu",),
    "flash": ("ecu",),
    "line": ("panel",),
    "run": ("station",),
    "station": ("operator",),
}


_ENDING_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")


#: the process's exit status as :func:`main` decided it; :func:`end_process` ends the process with it
_exit_status = 0


def _status(code: object) -> int:
    """The exit status Python gives ``SystemExit(code)``: None 0, an int itself, anything else 1."""
    if code is None:
        return 0
    return code if isinstance(code, int) else 1


def end_process() -> None:
    # The last atexit handler ends the process with the decided status at once. Past it Python's
    # own teardown (module finalization, XLA's threads and destructors) ran with the handlers
    # reset: a signal there killed the process by the signal (exit -2) or, ignored, left the exit
    # status the verdict although the signal came; no window is left now. Everything the command
    # wrote is closed by then (atomic writes, committed records; the exchange log's handler
    # flushes each line), and every other atexit handler was registered later, so it has run.
    import contextlib
    import os
    import sys

    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed pipe: nothing more can be said
            stream.flush()
    os._exit(_exit_status)


def _exit_at_once_on_a_signal() -> None:
    """From here on the outcome is decided and said: a signal (a second Ctrl-C while threads
    and atexit handlers finish) ends the process at once with exit 2 until :func:`end_process` ends
    it with the decided status; never the signal's own death (130)."""
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

    from eol_cal.numerics.blas import limit_blas_threads

    global _exit_status
    atexit.register(end_process)  # registered first: runs last
    limit_blas_threads()
    try:
        try:
            cli(prog_name="eol-cal")
        except KeyboardInterrupt:
            # Ctrl-C before a command set its handlers (imports, option parsing): one line, exit 2
            from eol_cal.errors import Interrupted

            click.echo(f"error: {Interrupted()}", err=True)
            raise SystemExit(Interrupted.exit_code) from None
    except SystemExit as exc:
        _exit_status = _status(exc.code)
        raise
    except BaseException:  # a bug: Python prints its traceback before the atexit handlers run
        _exit_status = 1
        raise
    finally:
        _exit_at_once_on_a_signal()


if __name__ == "__main__":
    main()
