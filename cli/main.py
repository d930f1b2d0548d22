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


def main() -> None:
    try:
        cli(prog_name="eol-cal")
    except KeyboardInterrupt:
        # Ctrl-C before a command set its handlers (imports, option parsing): one line, exit 2
        from eol_cal.errors import Interrupted

        click.echo(f"error: {Interrupted()}", err=True)
        raise SystemExit(Interrupted.exit_code) from None


if __name__ == "__main__":
    main()
