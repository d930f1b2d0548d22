"""The command line starts without what it does not need (issue 37): ``eol-cal --help`` imports
no numpy, ``eol-cal capture info`` no JAX, scipy or plotting; each command's module is imported
when the command is asked for, so the table of where commands live must hold every command."""

from __future__ import annotations

import os
import subprocess
import sys

import click
import pytest

import cli.main as main
from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture

#: what a command that reads no capture, or reads one without fitting it, has no use for
HEAVY = ("jax", "jaxlib", "scipy", "matplotlib", "sqlalchemy", "pint", "asammdf", "optimistix", "can", "dask",
         "distributed")

_PROBE = """
import contextlib, io, runpy, sys
sys.argv = ["eol-cal", *sys.argv[1:]]
out = io.StringIO()
try:
    with contextlib.redirect_stdout(out):
        runpy.run_module("cli.main", run_name="__main__")
except SystemExit as exc:
    code = exc.code
print(code, *sorted({m.split(".")[0] for m in sys.modules}), file=sys.stderr)
"""


def _top_modules(*args: str) -> tuple[object, set[str]]:
    """(exit code, top-level packages imported) of ``eol-cal ARGS`` in a fresh interpreter."""
    res = subprocess.run([sys.executable, "-c", _PROBE, *args], capture_output=True, text=True, timeout=300,
                         env={k: v for k, v in os.environ.items() if not k.startswith("EOL_CAL_")})
    code, *mods = res.stderr.strip().splitlines()[-1].split()
    return code, set(mods)


@pytest.mark.slow  # a process of its own
def test_help_imports_no_numpy_nor_anything_heavy():
    code, mods = _top_modules("--help")
    assert code == "0"
    assert mods & {"numpy", *HEAVY} == set()


@pytest.mark.slow  # a process of its own
def test_capture_info_imports_nothing_heavy(tmp_path):
    path = tmp_path / "one.csv"
    write_capture(synthetic_capture(rpm=600.0, i_qo=65.0, seconds=0.1, seed=1, serial="B-1"), path)
    code, mods = _top_modules("capture", "info", str(path))
    assert code == "0" and "numpy" in mods  # it did read the file
    assert mods & set(HEAVY) == set()


def _tree_modules(cmd: click.Command) -> set[str]:
    """The command modules (``cli.x`` -> ``x``) of a command and every subcommand under it."""
    module = cmd.callback.__module__ if cmd.callback is not None else ""
    found = {module.removeprefix("cli.")} if module.startswith("cli.") else set()
    for sub in (cmd.commands.values() if isinstance(cmd, click.Group) else ()):
        found |= _tree_modules(sub)
    return found


def test_every_command_is_found_where_the_table_says():
    """Every command of every module, its subcommands included, is built by the modules
    :func:`cli.main.modules_of` imports for its name (a command moved to another module, or a
    module that adds a subcommand to another's group, needs its line in ``_COMMAND_HOME``)."""
    main._load(main._COMMAND_MODULES)
    assert set(main.cli.commands) == set(main.cli.list_commands(click.Context(main.cli)))
    for name, cmd in main.cli.commands.items():
        assert _tree_modules(cmd) <= set(main.modules_of(name)), name
    assert set(main._COMMAND_HOME) <= set(main.cli.commands)  # no stale line


@pytest.mark.slow  # a process of its own: this one's commands may all be loaded already
def test_a_group_is_whole_when_another_command_of_its_module_came_first():
    probe = ("import click, cli.main as m\n"
             "ctx = click.Context(m.cli)\n"
             "m.cli.get_command(ctx, 'flash')  # cli/ecu.py: the ecu group, without cli/restore.py's subcommand\n"
             "print(*sorted(m.cli.get_command(ctx, 'ecu').commands))")
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300, check=True)
    assert "restore" in res.stdout.split()


_CAN_PROBE = """
import sys
{first}
import eol_cal.ecu.client, can
bus = can.Bus(interface="virtual", channel="probe", receive_own_messages=True)
bus.send(can.Message(arbitration_id=0x7E0, data=b"\\x02\\x10\\x03", is_extended_id=False))
got = bus.recv(1.0)
bus.shutdown()
import can.io.mf4 as mf4
print(got.arbitration_id == 0x7E0, "pandas" in sys.modules, mf4.asammdf is not None)
"""


@pytest.mark.slow  # processes of their own
def test_python_can_is_imported_without_its_mf4_logger_unless_asammdf_came_first():
    """python-can imports asammdf (and pandas) for its MF4 logger, 0.6-0.7 CPU s a process that
    opens the bus; eol-cal never logs CAN to MF4. ``import eol_cal`` masks it for python-can's first
    import, from any module; the bus still works, and a process that imported asammdf before keeps
    python-can's MF4 format."""
    for first, expect in (("", "True False False"), ("import asammdf", "True True True")):
        res = subprocess.run([sys.executable, "-c", _CAN_PROBE.format(first=first)], capture_output=True,
                             text=True, timeout=300)
        assert res.stdout.split()[-3:] == expect.split(), (first, res.stdout, res.stderr)
