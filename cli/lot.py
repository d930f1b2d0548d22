"""``eol-cal lot report``: the lot page of a records database."""

from __future__ import annotations

from pathlib import Path

import click

from cli.common import RECORDS_DB, CommandExit, console, handle_errors, kind_option
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


def day_options(func):
    """``--since`` and ``--until``: UTC days, inclusive (:func:`_date` checks them)."""
    func = click.option("--until", default=None, metavar="YYYY-MM-DD", help="Only runs started on this UTC day or earlier.")(func)
    return click.option("--since", default=None, metavar="YYYY-MM-DD", help="Only runs started on this UTC day or later.")(func)


def lot_filters(func):
    """``--db`` and the filters that choose a lot: ``--variant``, ``--since``, ``--until``, ``--station``."""
    func = click.option("--station", default=None, help="Only this station.")(func)
    func = day_options(func)
    func = click.option("--variant", default=None, help="Only this product variant.")(func)
    return click.option("--db", required=True, type=RECORDS_DB,
                        help="Records database: a SQLite file or postgresql://user@host:port/db.")(func)


def min_n_option(func):
    """``--min-n`` (``$EOL_CAL_MIN_N``): the minimum n of capability indices and control limits."""
    return click.option("--min-n", default=None, type=click.IntRange(min=2), envvar="EOL_CAL_MIN_N",
                        help="Fewest values that give a capability index, a control limit or Cg/Cgk [default: 25; "
                             "$EOL_CAL_MIN_N]; fewer: shown as 'n = 7 < 25'.")(func)


@lot_group.command("report")
@lot_filters
@min_n_option
@click.option("--baseline", "baseline_name", default=None, metavar="NAME",
              help="Draw this stored baseline's frozen limits and list the runs that break a rule.")
@click.option("-o", "--out", "out", default=Path("lot.html"), show_default=True,
              type=click.Path(dir_okay=False, path_type=Path), help="The page to write (one self-contained HTML file).")
@handle_errors
@io_paths(inputs=("db",), outputs=("out",))
def report_cmd(db, variant, since, until, station, min_n, baseline_name, out) -> None:
    """Write the lot page: yield and counts, distributions with the limits (phases on the circle),
    capability per variant and station, control charts per station (against a frozen baseline
    with the run rules when given), the motors nearest their limits with links to their reports,
    the refused runs with their own Pareto. One file that opens offline in a browser. The
    statistics are of the production runs (docs/records.md, "Run kinds")."""
    from eol_cal.errors import InputError
    from eol_cal.lot.spc import DEFAULT_MIN_N
    from eol_cal.report.lot import select_records, write_lot_page
    from eol_cal.station.records import db_label
    from eol_cal.station.records_query import query_records

    first, last = _date(since, "since"), _date(until, "until")
    baseline = None
    if baseline_name is not None:
        from eol_cal.lot.baseline import load

        baseline = load(db, baseline_name)
    records = select_records(query_records(db), variant, first, last, station)  # every kind: the page sorts them
    try:
        path = write_lot_page(records, out, title=db_label(db),
                              filters={"variant": variant, "since": since, "until": until, "station": station},
                              min_n=DEFAULT_MIN_N if min_n is None else min_n, baseline=baseline)
    except OSError as exc:
        raise InputError(str(out), None, f"cannot write: {exc.strerror or exc}") from None
    console.print(f"lot page: {path} ({len(records)} runs)")


def _fmt(x, digits: int = 4) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


@lot_group.command("stats")
@lot_filters
@min_n_option
@click.option("--baseline", "baseline_name", default=None, metavar="NAME",
              help="Judge the runs against this stored baseline (eol-cal lot baseline): Western Electric rules 1-4; "
                   "exit 1 when one fires.")
@click.option("--quantity", "judged", multiple=True, metavar="KEY",
              help="A quantity to judge against the baseline (repeat) [default: k6, pp_after_pct].")
@kind_option("the runs the statistics are of.")
@click.option("--json", "as_json", is_flag=True, help="Print the statistics as one JSON document.")
@click.option("--csv", "csv_file", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the selected runs (one row each, the database's columns, units in the header; with "
                   "--baseline the rules each run is part of) as CSV.")
@handle_errors
@io_paths(inputs=("db",), outputs=("csv_file",))
def stats_cmd(db, variant, since, until, station, min_n, baseline_name, judged, kind, as_json, csv_file) -> None:
    """Lot statistics of the production runs (--kind for others): per quantity count, mean, sd,
    percentiles (phases on the circle), Cp/Cpk per variant and station against the variant's
    limit; first-pass yield; failure causes as a Pareto; individuals / moving-range control
    limits per station; the refused runs and their reasons apart. Capability and limits need
    --min-n values. With --baseline the runs are judged against its frozen lines (exit 1 when a
    rule fires). Definitions: docs/spc.md."""
    from cli.common import print_json
    from eol_cal.errors import InputError
    from eol_cal.lot.columns import CHARTED, QUANTITIES, read_lots
    from eol_cal.lot.spc import DEFAULT_MIN_N
    from eol_cal.lot.summary import LOT_STATS_SCHEMA, lot_summary, write_runs_csv
    from eol_cal.station.records import db_label

    keys = [q.key for q in QUANTITIES]
    for key in judged:
        if key not in keys:
            raise InputError(None, "--quantity", f"{key!r} is not one of {', '.join(keys)}")
    if judged and baseline_name is None:
        raise InputError(None, "--quantity", "judges against a baseline: give --baseline NAME")
    first, last = _date(since, "since"), _date(until, "until")
    filters = dict(variant=variant, station=station, since=first and first.isoformat(),
                   until=last and last.isoformat())
    min_n = DEFAULT_MIN_N if min_n is None else min_n
    baseline = None
    if baseline_name is not None:
        from eol_cal.lot.baseline import load

        baseline = load(db, baseline_name)
    lot, refusals = read_lots(db, **filters, kind=kind, also=("refusal",))
    doc = lot_summary(lot, refusals, min_n, baseline, tuple(judged) or CHARTED)
    if csv_file is not None:
        from eol_cal.lot.spc_stats import rules_by_run

        try:
            runs = write_runs_csv(csv_file, db, rules_by_run(doc["violations"]) if baseline else None, **filters,
                                  kind=kind)
        except OSError as exc:
            raise InputError(str(csv_file), None, f"cannot write: {exc.strerror or exc}") from None
    if as_json:
        print_json({"schema": LOT_STATS_SCHEMA, "db": db_label(db),
                    "filters": {"variant": variant, "since": since, "until": until, "station": station, "kind": kind},
                    **doc})
    else:
        _print_stats(db_label(db), doc, kind)
        if csv_file is not None:
            console.print(f"csv: {csv_file} ({runs} runs)")
    if doc["violations"]:
        raise CommandExit(1)


def _print_stats(label: str, doc: dict, kind: str) -> None:
    from rich.table import Table

    from eol_cal.lot.spc_stats import gated_text

    fpy = doc["first_pass_yield"]
    console.print(f"{label}: {doc['runs']} {'' if kind == 'all' else kind + ' '}run(s) of {doc['motors']} "
                  f"motor(s); pass {doc['verdicts']['pass']}, fail {doc['verdicts']['fail']}, error "
                  f"{doc['verdicts']['error']}; first-pass yield " + ("-" if fpy is None else f"{100 * fpy:.1f} %")
                  + f"; refused {doc['refusals']['runs']} (nothing written, not in these figures); minimum n {doc['min_n']}")
    t = Table(title="quantities (phases: circular mean and sd)")
    for col in ("quantity", "unit", "n", "mean", "sd", "p5", "p50", "p95", "limit", "Cp", "Cpk", "Ppk"):
        t.add_column(col, justify="left" if col in ("quantity", "unit") else "right")
    for q in doc["quantities"]:
        p = q["percentiles"]
        t.add_row(q["title"] + (" (circular)" if q["circular"] else ""), q["unit"], str(q["count"]), _fmt(q["mean"]),
                  _fmt(q["sd"], 3), _fmt(p["p5"]), _fmt(p["p50"]), _fmt(p["p95"]), _fmt(q["limit"]),
                  *(gated_text(q[k], q[f"{k}_reason"]) if q["limit_key"] else "-" for k in ("cp", "cpk", "ppk")))
    console.print(t)
    t = Table(title="capability per variant and station")
    for col in ("quantity", "variant", "station", "n", "limit", "Cpk", "Ppk"):
        t.add_column(col, justify="left" if col in ("quantity", "variant", "station") else "right")
    for q in doc["quantities"]:
        for g in q["capability"]:
            t.add_row(q["key"], g["variant"], g["station"] or "all", str(g["n"]), _fmt(g["limit"]),
                      gated_text(g["cpk"], g["cpk_reason"]), gated_text(g["ppk"], g["ppk_reason"]))
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
    t = Table(title="control limits per station (I-MR, the station's own runs)")
    for col in ("station", "quantity", "n", "centre", "LCL", "UCL", "MR centre", "MR UCL"):
        t.add_column(col, justify="left" if col in ("station", "quantity") else "right")
    for st, qs in doc["control"].items():
        for key, cl in qs.items():
            figures = ([_fmt(cl[k]) for k in ("center", "lcl", "ucl", "mr_center", "mr_ucl")] if cl["reason"] is None
                       else [cl["reason"], "", "", "", ""])
            t.add_row(st, key, str(cl["n"]), *figures)
    console.print(t)
    if doc["baseline"] is not None:
        b = doc["baseline"]
        console.print(f"baseline {b['name']!r} ({b['created_at'][:19]} UTC, {b['runs']} runs, "
                      f"{b['filters'].get('since') or 'any'} .. {b['filters'].get('until') or 'any'})")
        t = Table(title="run rules against the baseline (Western Electric 1-4)")
        for col in ("quantity", "variant", "station", "rule", "runs"):
            t.add_column(col)
        for v in doc["violations"]:
            t.add_row(v["quantity"], v["variant"], v["station"], v["text"],
                      ", ".join(f"{s} {str(a)[:16]}" for s, a in zip(v["serials"], v["started_at"])))
        console.print(t)
        unjudged = [j for j in doc["judged"] if j["reason"]]
        for j in unjudged:
            console.print(f"  not judged: {j['quantity']} {j['variant']} {j['station']}: {j['reason']}")
        console.print(f"{len(doc['violations'])} rule violation(s)" + (" (exit 1)" if doc["violations"] else ""))


@lot_group.command("baseline")
@lot_filters
@click.option("--name", required=True, help="The baseline's name (lot stats --baseline NAME).")
@min_n_option
@click.option("--replace", is_flag=True, help="Replace a baseline of that name.")
@click.option("--json", "as_json", is_flag=True, help="Print the stored baseline as JSON.")
@handle_errors
def baseline_cmd(db, name, since, until, variant, station, min_n, replace, as_json) -> None:
    """Freeze centre lines and control limits per quantity, variant and station from the runs of
    a period, and store them in the database: later `lot stats --baseline NAME` judges new runs
    against them (docs/spc.md). Groups with fewer than --min-n runs get no limits (the reason is
    stored)."""
    from cli.common import print_json
    from eol_cal.errors import InputError
    from eol_cal.lot.baseline import baseline_document, baseline_of_db, store
    from eol_cal.lot.spc import DEFAULT_MIN_N
    from eol_cal.station.records import db_label

    first, last = _date(since, "since"), _date(until, "until")
    filters = dict(since=first and first.isoformat(), until=last and last.isoformat(), variant=variant, station=station)
    min_n = DEFAULT_MIN_N if min_n is None else min_n
    b = baseline_of_db(db, name, filters, min_n)
    if all(line.center is None for line in b.lines.values()):
        reasons = sorted({str(line.reason) for line in b.lines.values()})
        raise InputError(db_label(db), "baseline", f"no variant and station with limits ({'; '.join(reasons)}): nothing stored")
    store(db, b, replace=replace)
    doc = {**baseline_document(b), "db": db_label(db)}
    if as_json:
        print_json(doc)
        return
    from rich.table import Table

    t = Table(title=f"baseline {name}: {b.runs} run(s), min n {min_n}")
    for col in ("quantity", "unit", "variant", "station", "n", "centre", "sigma", "LCL", "UCL"):
        t.add_column(col, justify="left" if col in ("quantity", "unit", "variant", "station") else "right")
    for line in doc["lines"]:
        figures = ([_fmt(line[k]) for k in ("center", "sigma", "lcl", "ucl")] if line["reason"] is None
                   else [line["reason"], "", "", ""])
        t.add_row(line["quantity"], line["unit"], line["variant"], line["station"], str(line["n"]), *figures)
    console.print(t)
    console.print(f"stored in {db_label(db)} as {name!r}")


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
