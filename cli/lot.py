"""``eol-cal lot report``: the lot page of a records database."""

from __future__ import annotations

from pathlib import Path

import click

from cli.common import RECORDS_DB, console, handle_errors


def _date(value: str | None, name: str):
    import datetime as dt

    from eol_cal.errors import InputError

    if value is None:
        return None
    try:
        return dt.date.fromisoformat(value)
    except ValueError:
        raise InputError(None, name, f"{value!r}: expected YYYY-MM-DD") from None


@click.group("lot")
def lot_group() -> None:
    """A lot of motors: the page quality engineers look at."""


@lot_group.command("report")
@click.option("--db", required=True, type=RECORDS_DB, help="Records database: a SQLite file or postgresql://user@host:port/db.")
@click.option("--variant", default=None, help="Only this product variant.")
@click.option("--since", default=None, metavar="YYYY-MM-DD", help="Only runs started on this UTC day or later.")
@click.option("--until", default=None, metavar="YYYY-MM-DD", help="Only runs started on this UTC day or earlier.")
@click.option("--station", default=None, help="Only this station.")
@click.option("-o", "--out", "out", default=Path("lot.html"), show_default=True,
              type=click.Path(dir_okay=False, path_type=Path), help="The page to write (one self-contained HTML file).")
@handle_errors
def report_cmd(db, variant, since, until, station, out) -> None:
    """Write the lot page: yield and counts, distributions with the limits, control charts per
    station, the motors nearest their limits with links to their reports. One file that opens
    offline in a browser."""
    from eol_cal.errors import InputError
    from eol_cal.report.lot import select_records, write_lot_page
    from eol_cal.station.records import db_label, query_records

    first, last = _date(since, "since"), _date(until, "until")
    records = select_records(query_records(db), variant, first, last, station)
    try:
        path = write_lot_page(records, out, title=db_label(db),
                              filters={"variant": variant, "since": since, "until": until, "station": station})
    except OSError as exc:
        raise InputError(str(out), None, f"cannot write: {exc.strerror or exc}") from None
    console.print(f"lot page: {path} ({len(records)} runs)")


COMMANDS = [lot_group]
