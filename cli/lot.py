"""``eol-cal lot report``: the lot page of a records database."""

from __future__ import annotations

from pathlib import Path

import click

from cli.common import RECORDS_DB, console, handle_errors, kind_option
from cli.paths import io_paths


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
@io_paths(inputs=("db",), outputs=("out",))
def report_cmd(db, variant, since, until, station, out) -> None:
    """Write the lot page: yield and counts, distributions with the limits, control charts per
    station, the motors nearest their limits with links to their reports, the refused runs with
    their own Pareto. One file that opens offline in a browser. The statistics are of the
    production runs (docs/records.md, "Run kinds")."""
    from eol_cal.errors import InputError
    from eol_cal.report.lot import select_records, write_lot_page
    from eol_cal.station.records import db_label
    from eol_cal.station.records_query import query_records

    first, last = _date(since, "since"), _date(until, "until")
    records = select_records(query_records(db), variant, first, last, station)  # every kind: the page sorts them
    try:
        path = write_lot_page(records, out, title=db_label(db),
                              filters={"variant": variant, "since": since, "until": until, "station": station})
    except OSError as exc:
        raise InputError(str(out), None, f"cannot write: {exc.strerror or exc}") from None
    console.print(f"lot page: {path} ({len(records)} runs)")


def _fmt(x, digits: int = 4) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


@lot_group.command("stats")
@click.option("--db", required=True, type=RECORDS_DB, help="Records database: a SQLite file or postgresql://user@host:port/db.")
@click.option("--variant", default=None, help="Only this product variant.")
@click.option("--since", default=None, metavar="YYYY-MM-DD", help="Only runs started on this UTC day or later.")
@click.option("--until", default=None, metavar="YYYY-MM-DD", help="Only runs started on this UTC day or earlier.")
@click.option("--station", default=None, help="Only this station.")
@kind_option("the runs the statistics are of.")
@click.option("--json", "as_json", is_flag=True, help="Print the statistics as one JSON document.")
@click.option("--csv", "csv_file", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the selected runs (one row each, the database's columns, units in the header) as CSV.")
@handle_errors
@io_paths(inputs=("db",), outputs=("csv_file",))
def stats_cmd(db, variant, since, until, station, kind, as_json, csv_file) -> None:
    """Lot statistics of the production runs (--kind for others): per quantity count, mean, sd,
    percentiles and Cp/Cpk against the variant's limit; first-pass yield; failure causes as a
    Pareto; individuals / moving-range control limits per station; the refused runs and their
    reasons apart."""
    from cli.common import print_json
    from eol_cal.lot.columns import read_lots
    from eol_cal.lot.summary import LOT_STATS_SCHEMA, lot_summary, write_runs_csv
    from eol_cal.station.records import db_label

    first, last = _date(since, "since"), _date(until, "until")
    filters = dict(variant=variant, station=station, since=first and first.isoformat(),
                   until=last and last.isoformat())
    lot, refusals = read_lots(db, **filters, kind=kind, also=("refusal",))
    doc = lot_summary(lot, refusals)
    if csv_file is not None:
        from eol_cal.errors import InputError

        try:
            runs = write_runs_csv(csv_file, db, **filters, kind=kind)
        except OSError as exc:
            raise InputError(str(csv_file), None, f"cannot write: {exc.strerror or exc}") from None
    if as_json:
        print_json({"schema": LOT_STATS_SCHEMA, "db": db_label(db),
                    "filters": {"variant": variant, "since": since, "until": until, "station": station, "kind": kind},
                    **doc})
        return
    from rich.table import Table

    fpy = doc["first_pass_yield"]
    console.print(f"{db_label(db)}: {doc['runs']} {'' if kind == 'all' else kind + ' '}run(s) of {doc['motors']} "
                  f"motor(s); pass {doc['verdicts']['pass']}, fail {doc['verdicts']['fail']}, error "
                  f"{doc['verdicts']['error']}; first-pass yield " + ("-" if fpy is None else f"{100 * fpy:.1f} %")
                  + f"; refused {doc['refusals']['runs']} (nothing written, not in these figures)")
    t = Table(title="quantities")
    for col in ("quantity", "unit", "n", "mean", "sd", "p5", "p50", "p95", "limit", "Cp", "Cpk", "Ppk"):
        t.add_column(col, justify="left" if col in ("quantity", "unit") else "right")
    for q in doc["quantities"]:
        p = q["percentiles"]
        t.add_row(q["title"], q["unit"], str(q["count"]), _fmt(q["mean"]), _fmt(q["sd"], 3), _fmt(p["p5"]),
                  _fmt(p["p50"]), _fmt(p["p95"]), _fmt(q["limit"]), _fmt(q["cp"], 3), _fmt(q["cpk"], 3), _fmt(q["ppk"], 3))
    console.print(t)
    if doc["pareto"]:
        t = Table(title="failure causes (Pareto)")
        for col in ("cause", "runs", "cumulative"):
            t.add_column(col, justify="left" if col == "cause" else "right")
        for c in doc["pareto"]:
            t.add_row(c["cause"], str(c["runs"]), f"{100 * c['cumulative']:.0f} %")
        console.print(t)
    if doc["refusals"]["pareto"]:
        t = Table(title="refused runs by reason (Pareto)")
        for col in ("reason", "runs", "cumulative"):
            t.add_column(col, justify="left" if col == "reason" else "right")
        for c in doc["refusals"]["pareto"]:
            t.add_row(c["cause"], str(c["runs"]), f"{100 * c['cumulative']:.0f} %")
        console.print(t)
    t = Table(title="control limits per station (I-MR)")
    for col in ("station", "quantity", "runs", "centre", "LCL", "UCL", "MR centre", "MR UCL"):
        t.add_column(col, justify="left" if col in ("station", "quantity") else "right")
    for st, qs in doc["control"].items():
        for key, cl in qs.items():
            t.add_row(st, key, str(cl["runs"]), _fmt(cl["center"]), _fmt(cl["lcl"]), _fmt(cl["ucl"]),
                      _fmt(cl["mr_center"]), _fmt(cl["mr_ucl"]))
    console.print(t)
    if csv_file is not None:
        console.print(f"csv: {csv_file} ({runs} runs)")


@lot_group.command("diff")
@click.option("--db", required=True, type=RECORDS_DB, help="Records database: a SQLite file or postgresql://user@host:port/db.")
@click.argument("results", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@kind_option("each serial's latest run of this kind is compared.")
@click.option("--json", "as_json", is_flag=True, help="Print the changes as JSON.")
@handle_errors
def diff_cmd(db, results, kind, as_json) -> None:
    """Which motors a refit (`eol-cal refit -o RESULTS`) judges otherwise than their latest recorded
    run: the refit's verdict and failed limits against the fit-stage checks the record carries
    (a refit makes no compensated capture: the ripple limits are not compared)."""
    from cli.common import print_json
    from eol_cal.lot.diff import LOT_DIFF_SCHEMA, verdict_changes
    from eol_cal.lot.refit import read_rows
    from eol_cal.station.records_query import query_records

    rows = [r for path in results for r in read_rows(path)]
    doc = verdict_changes(query_records(db, kind=kind), rows, kind=kind)
    if as_json:
        print_json({"schema": LOT_DIFF_SCHEMA, "kind": kind, **doc})
        return
    from rich.table import Table

    changes = doc["changes"]
    t = Table(title=f"{len(changes)} of {doc['compared']} compared motor(s) change (fit-stage limits); "
                    f"{doc['not_compared']} not compared, {doc['errors']} refit error(s)")
    for col in ("serial", "recorded", "refit", "now failing", "no longer failing", f"k6 recorded\n{doc['k6_unit']}",
                f"k6 refit\n{doc['k6_unit']}", "reasons"):
        t.add_column(col)
    for c in changes:
        t.add_row(c["serial"], c["recorded"], c["refit"], ", ".join(c["newly_failing"]) or "-",
                  ", ".join(c["no_longer_failing"]) or "-", _fmt(c["k6_recorded"]), _fmt(c["k6_refit"]),
                  "; ".join(c["reasons"]))
    console.print(t)


COMMANDS = [lot_group]
