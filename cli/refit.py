"""``eol-cal refit``: refit a lot's captures on a Dask cluster."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from cli.common import CommandExit, console, err_console, handle_errors, kind_option
from cli.paths import io_paths


#: seconds to reach a --scheduler before giving up (distributed's own default is 30)
SCHEDULER_TIMEOUT_S = 10


def scheduler_address(text: str) -> str:
    """A Dask scheduler's address, ``tcp://HOST:PORT`` (``tls://`` too; a bare ``HOST:PORT`` is
    tcp): checked before any cluster is reached (a malformed one was a ValueError traceback)."""
    from eol_cal.infra.address import parse_host_port
    from eol_cal.errors import InputError

    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    if scheme not in ("tcp", "tls"):
        raise InputError(None, "scheduler", f"{text!r}: expected tcp://HOST:PORT (or tls://)")
    host, port = parse_host_port(rest, "scheduler")
    return f"{scheme}://{host}:{port}"


def cluster_client(stack: contextlib.ExitStack, scheduler: str | None, workers: int):
    """A ``distributed`` client of ``scheduler`` (checked first; one that cannot be reached within
    :data:`SCHEDULER_TIMEOUT_S` is exit 2 naming it, not distributed's traceback), else of a local
    cluster of ``workers`` processes; closed with ``stack``."""
    from distributed import Client

    from eol_cal.errors import InputError
    from eol_cal.lot.cluster import local_cluster

    address = None if scheduler is None else scheduler_address(scheduler)
    cluster = None if address else stack.enter_context(local_cluster(workers))
    try:
        return stack.enter_context(Client(address or cluster, timeout=SCHEDULER_TIMEOUT_S))
    except (OSError, TimeoutError, ValueError) as exc:  # down, refusing, or not a scheduler
        raise InputError(None, "scheduler", f"cannot connect to {address}: {exc}") from None


def _check_lot_inputs(limits_file: str | None, variant: str | None, bench: str, motor: str) -> None:
    """What every task would read, read once here: a bad limits file, variant, bench or motor is
    bad input (exit 2) before the cluster starts, not an error row per capture (exit 1)."""
    from eol_cal.errors import InputError
    from eol_cal.domain.bench_mechanics import mechanics_or_rigid
    from eol_cal.domain.motor_params import load_motor
    from eol_cal.records.limits import load_limits

    if limits_file is not None:
        load_limits(limits_file, variant)
    elif variant is not None:
        raise InputError(None, "variant", "given without --limits")
    mechanics_or_rigid(bench)
    load_motor(motor)


@click.command("refit")
@click.argument("captures", nargs=-1, required=True)
@click.option("--scheduler", default=None, metavar="tcp://HOST:8786", help="A running Dask scheduler to use.")
@click.option("--workers", type=click.IntRange(1, 256), default=2, show_default=True,
              help="Worker processes of the local cluster (127.0.0.1) when no --scheduler is given.")
@click.option("--limits", "limits_file", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Limits file: each row gets the verdict the fit's limits give.")
@click.option("--variant", default=None, help="Variant in the limits file.")
@click.option("--bench", default="paper", show_default=True, metavar="NAME|FILE.toml",
              help="Dyno bench the captures were made on (as for fit); 'none': rigid coupling.")
@click.option("--motor", default="paper", show_default=True, help="Motor preset the runs were made with.")
@click.option("-o", "--out", "out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Results: .parquet or .jsonl, one row per capture, keyed by serial.")
@kind_option("station run directories whose record is of another kind are left out.")
@handle_errors
@io_paths(inputs=("captures", "limits_file", "bench", "motor"), outputs=("out",))
def refit_cmd(captures, scheduler, workers, limits_file, variant, bench, motor, out, kind) -> None:
    """Refit every capture (directories of station runs: their before.mf4; files; globs) on a
    `distributed` cluster, a few motor runs per task, with the station's fit; rows keyed by serial."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.errors import InputError
    from eol_cal.lot.cluster import RefitWorkerSetup
    from eol_cal.lot.refit import find_captures, refit_lot, write_rows

    if out.suffix not in (".parquet", ".jsonl"):
        raise InputError(str(out), None, "results file must end in .jsonl or .parquet")
    paths = find_captures(captures, kind)
    _check_lot_inputs(limits_file, variant, bench, motor)
    if scheduler is not None:
        scheduler_address(scheduler)  # before the captures are read
    cache_dir = default_cache_dir()
    with contextlib.ExitStack() as stack:
        client = cluster_client(stack, scheduler, workers)
        # every worker (one restarted after a crash too): JAX's persistent compile cache, the fit's
        # modules imported and frozen out of the garbage collector's walks
        client.register_plugin(RefitWorkerSetup(cache_dir))
        with Progress(TextColumn("refit"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      console=err_console, transient=False, refresh_per_second=2) as bar:
            task = bar.add_task("refit", total=len(paths))
            rows = refit_lot(paths, client, limits_file, variant, on_done=lambda _r: bar.advance(task),
                             bench=bench, motor=motor, cache_dir=cache_dir)
    write_rows(out, rows)
    bad = [r for r in rows if r["error"]]
    for r in bad:
        err_console.print(f"{r['capture']}: {r['error']}")
    verdicts = {v: sum(r["verdict"] == v for r in rows) for v in ("pass", "fail", "error")}
    console.print(f"refit {len(rows)} capture(s) -> {out}: " + ", ".join(f"{k} {n}" for k, n in verdicts.items()))
    if bad:
        raise CommandExit(1)


COMMANDS = [refit_cmd]
