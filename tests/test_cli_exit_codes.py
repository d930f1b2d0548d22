"""The CLI maps outcomes to exit codes in one place (cli/common.handle_errors)."""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from cli.common import CommandExit, handle_errors
from eol_cal.errors import CheckFailed, InputError

ROOT = Path(__file__).resolve().parents[1]


def test_no_command_calls_sys_exit() -> None:
    offenders = [
        f"{p.relative_to(ROOT)}:{n}"
        for p in sorted((ROOT / "cli").glob("*.py")) if p.name != "common.py"
        for n, line in enumerate(p.read_text().splitlines(), 1) if re.search(r"\bsys\.exit\(|\bexit\(", line)
    ]
    assert offenders == []


@pytest.mark.parametrize(("raised", "code", "stderr"), [
    (None, 0, ""),
    (CommandExit(0), 0, ""),
    (CommandExit(1), 1, ""),
    (CheckFailed("k6 over its limit"), 1, "error: k6 over its limit\n"),
    (InputError("fit.json", "k6", "not a number"), 2, "error: file fit.json, field 'k6': not a number\n"),
])
def test_handle_errors_maps_each_outcome(raised: BaseException | None, code: int, stderr: str) -> None:
    @click.command()
    @handle_errors
    def cmd() -> None:
        click.echo("out")
        if raised is not None:
            raise raised

    res = CliRunner().invoke(cmd, [])
    assert (res.exit_code, res.stdout, res.stderr) == (code, "out\n", stderr)
