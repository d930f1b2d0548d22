"""``eol-cal golden``: write or verify the firmware golden vectors (firmware contract, section 4)."""

from __future__ import annotations

import click

from cli.common import handle_errors
from cli.paths import io_paths

_DEFAULT_DIR = "firmware_params/golden"


@click.command("golden")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), help="write every vector set into DIR")
@click.option("--check", "check_dir", type=click.Path(file_okay=False), is_flag=False, flag_value=_DEFAULT_DIR,
              help=f"compare DIR (default {_DEFAULT_DIR}) with the Python reference; exit 1 on any difference")
@handle_errors
@io_paths(output_dirs=("out_dir",))
def golden(out_dir: str | None, check_dir: str | None) -> None:
    """Generate the golden vectors (--out DIR) or verify a checked-in set (--check [DIR])."""
    from eol_cal.errors import CheckFailed, InputError
    from eol_cal.firmware.golden import check_golden, vector_sets, write_golden

    if (out_dir is None) == (check_dir is None):
        raise InputError(None, "--out/--check", "give exactly one of --out DIR or --check [DIR]")
    if check_dir is not None:
        _readable_set(check_dir)  # at once, before the vector sets are computed
    sets = vector_sets()
    if out_dir is not None:
        doc = write_golden(out_dir, sets)
        for f in doc["files"]:
            click.echo(f"{out_dir}/{f['name']}: {f['rows']} rows, sha256 {f['sha256'][:16]}...")
        click.echo(f"{out_dir}/manifest.json: {len(doc['files'])} files")
        return
    problems = check_golden(check_dir, sets)
    if problems:
        for p in problems:
            click.echo(p, err=True)
        raise CheckFailed(f"{check_dir}: {len(problems)} difference(s) from the Python reference")
    rows = sum(len(vs.rows) for vs in sets.values())
    click.echo(f"{check_dir}: {len(sets)} files, {rows} rows identical to the Python reference")


COMMANDS = [golden]


def _readable_set(check_dir: str) -> None:
    """Refuse (exit 2) a --check directory that is missing or holds no readable manifest."""
    from pathlib import Path

    from eol_cal.errors import InputError
    from eol_cal.infra.inputs import read_text

    where = Path(check_dir)
    if not where.is_dir():
        hint = " (the default is relative to the project's root: run there or give --check DIR)" if \
            check_dir == _DEFAULT_DIR else ""
        raise InputError(check_dir, "--check", f"no such directory{hint}")
    read_text(where / "manifest.json")  # a missing, special or unreadable manifest is refused naming it
