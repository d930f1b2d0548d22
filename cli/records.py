"""``eol-cal records``: the run records of a database (by serial, day and kind, the pass rate, a plot
across the lot), the spool flushed into it, and ``records migrate``."""

from __future__ import annotations

from pathlib import Path

import click

from cli.common import RECORDS_DB, CommandExit, console, err_console, handle_errors, kind_option, print_json
from cli.paths import io_paths
from cli.station import rebuilt_pages, results_table


def _day(value: str | None) -> str | None:
    import datetime as dt

    if value is None:
        return None
    try:
        return dt.date.fromisoformat(value).isoformat()
    except ValueError:
        raise click.BadParameter(f"{value!r}: expected YYYY-MM-DD") from None


@click.group("records", invoke_without_command=True)
@click.option("--db", default="results.sqlite", show_default=True, type=RECORDS_DB,
              help="Records database: a SQLite file or postgresql://user@host:port/db.")
@click.option("--serial", default=None, help="Only this motor.")
@click.option("--day", default=None, metavar="YYYY-MM-DD", help="Only runs started on this UTC day.")
@kind_option("the list and --json [default: every kind; the summary counts production runs].", default="all")
@click.option("--json", "as_json", is_flag=True, help="Print the records and the summary as JSON.")
@click.option("--plot", "plot_file", type=click.Path(dir_okay=False, path_type=Path), help="PNG of k6 and p-p %% across the lot.")
@click.option("--flush", is_flag=True, help="First write spooled records into the database.")
@click.option("--spool-dir", type=click.Path(file_okay=False, path_type=Path), default=None, help="Spool directory (as for run).")
@click.pass_context
@handle_errors
@io_paths(outputs=("plot_file",), output_dirs=("spool_dir",), databases=("db",))
def records_cmd(ctx, db, serial, day, kind, as_json, plot_file, flush, spool_dir) -> None:
    """Query run records: by serial, day and kind, the pass rate, and a plot across the lot.

    The summary counts the production runs (measured motors); refusals (nothing written,
    nothing measured), restores and other kinds are counted apart. `eol-cal records migrate
    --db DB` brings a database to this version's schema."""
    from eol_cal.records.connect import db_label
    from eol_cal.records.query import query_records, summarise
    from eol_cal.records.spool import flush_spool

    if ctx.invoked_subcommand is not None:
        return
    day = _day(day)
    if flush:
        res = flush_spool(db, spool_dir)
        rebuilt_pages(res.records)
        msg = (f"flushed {res.flushed_files} spooled record(s) ({res.inserted} new) into {db_label(db)}"
               + (f"; {res.remaining} still waiting: {res.error}" if res.remaining else "")
               + (f"; {res.other_db} spooled for other databases" if res.other_db else "")
               + (f"; {res.in_flight} still being written by a running station (left for it)" if res.in_flight else ""))
        err_console.print(msg)
        for bad in res.bad_files:
            err_console.print(f"spool: {bad}; left alone")
        if res.remaining:
            raise CommandExit(2)
    skipped: list = []
    records = query_records(db, serial, day, skipped=skipped, kind=kind)
    for exc in skipped:  # a corrupt row costs only itself: reported, the others are listed
        click.echo(f"error: {exc}; skipped", err=True)
    summary = summarise(records)
    if plot_file is not None:
        from eol_cal.station.report_files import plot_lot

        plot_lot(plot_file, [r for r in records if r.kind == "production"],
                 title=f"{db_label(db)}" + (f", serial {serial}" if serial else "") + (f", {day}" if day else ""))
    if as_json:
        print_json({"schema": RECORDS_SCHEMA, "summary": summary, "records": [r.to_json() for r in records]})
        if skipped:
            raise CommandExit(2)
        return
    console.print(results_table(records, f"{db_label(db)}: {len(records)} run(s)"))
    rate = "-" if summary["pass_rate"] is None else f"{100 * summary['pass_rate']:.1f} %"
    others = ", ".join(f"{k} {n}" for k, n in summary["kinds"].items() if k != "production" and n)
    console.print(f"production runs {summary['runs']}: pass {summary['pass']}, fail {summary['fail']}, "
                  f"error {summary['error']}; pass rate {rate} (of runs that ended pass or fail); motors "
                  f"{summary['motors']}, {summary['motors_pass']} passing in their latest run"
                  + (f"; apart: {others}" if others else ""))
    if plot_file is not None:
        console.print(f"plot: {plot_file}")
    if skipped:
        raise CommandExit(2)


@records_cmd.command("migrate")
@click.option("--db", required=True, type=RECORDS_DB, help="Records database: a SQLite file or postgresql://user@host:port/db.")
@handle_errors
def migrate_cmd(db) -> None:
    """Create the records tables (runs, baselines, gate rules), or bring an older database to this
    version's schema, every table in one transaction."""
    from eol_cal.errors import InputError
    from eol_cal.records.connect import DB_ERRORS, db_label
    from eol_cal.records.migrations import migrate

    try:
        before, now = migrate(db)
    except DB_ERRORS as exc:
        raise InputError(db_label(db), None, f"cannot migrate: {str(exc).splitlines()[0]}") from None
    what = "created" if before is None else ("already at" if before == now else f"migrated from version {before} to")
    console.print(f"{db_label(db)}: {what} schema version {now}")


#: the ``schema`` of ``eol-cal records --json``
RECORDS_SCHEMA = "eol-cal/records/2"

COMMANDS = [records_cmd]
