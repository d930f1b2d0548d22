"""``eol-cal lot report``: the lot page of a records database."""

from __future__ import annotations

from pathlib import Path

import click

from cli.common import RECORDS_DB, CommandExit, console, handle_errors, kind_option
from cli.paths import io_paths


def parse_date(value: str | None, name: str):
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
    """``--since`` and ``--until``: UTC days, inclusive (:func:`parse_date` checks them)."""
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
@kind_option("the runs the statistics and charts are of (simulated: a lot simulate's what-if lot, with --station sim:NAME).")
@click.option("-o", "--out", "out", default=Path("lot.html"), show_default=True,
              type=click.Path(dir_okay=False, path_type=Path), help="The page to write (one self-contained HTML file).")
@handle_errors
@io_paths(outputs=("out",), databases=("db",))
def report_cmd(db, variant, since, until, station, min_n, baseline_name, kind, out) -> None:
    """Write the lot page: yield and counts, distributions with the limits (phases on the circle),
    capability per variant and station, control charts per station (against a frozen baseline
    with the run rules when given), the motors nearest their limits with links to their reports,
    the refused runs with their own Pareto. One file that opens offline in a browser. The
    statistics are of the production runs unless --kind says otherwise (docs/records.md, "Run kinds")."""
    from eol_cal.errors import InputError
    from eol_cal.lot.spc import DEFAULT_MIN_N
    from eol_cal.lot.lot_page import select_records, write_lot_page
    from eol_cal.records.connect import db_label
    from eol_cal.records.query import query_records

    first, last = parse_date(since, "since"), parse_date(until, "until")
    baseline = None
    if baseline_name is not None:
        from eol_cal.lot.baseline import load

        baseline = load(db, baseline_name)
    records = select_records(query_records(db), variant, first, last, station)  # every kind: the page sorts them
    try:
        path = write_lot_page(records, out, title=db_label(db), kind=kind,
                              filters={"variant": variant, "since": since, "until": until, "station": station,
                                       "kind": kind},
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
              help="Judge the runs against this stored baseline (eol-cal lot baseline): Nelson's rules 1, 2, 3, 5, 6; "
                   "exit 1 when one fires.")
@click.option("--quantity", "judged", multiple=True, metavar="KEY",
              help="A quantity to judge against the baseline (repeat) [default: k6, pp_after_pct].")
@kind_option("the runs the statistics are of.")
@click.option("--json", "as_json", is_flag=True, help="Print the statistics as one JSON document.")
@click.option("--csv", "csv_file", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the selected runs (one row each, the database's columns, units in the header; with "
                   "--baseline the rules each run is part of) as CSV.")
@handle_errors
@io_paths(outputs=("csv_file",), databases=("db",))
def stats_cmd(db, variant, since, until, station, min_n, baseline_name, judged, kind, as_json, csv_file) -> None:
    """Lot statistics of the production runs (--kind for others): per quantity count, mean, sd,
    percentiles (phases on the circle), Cp/Cpk per variant and station against the variant's
    limit; first-pass yield; failure causes as a Pareto; individuals / moving-range control
    limits per station; the refused runs and their reasons apart. Capability and limits need
    --min-n values. With --baseline the runs are judged against its frozen lines (exit 1 when a
    rule fires). Definitions: docs/spc.md."""
    from cli.common import print_json
    from eol_cal.errors import InputError
    from eol_cal.lot.runs import CHARTED, QUANTITIES, read_lots
    from eol_cal.lot.spc import DEFAULT_MIN_N
    from eol_cal.lot.summary import LOT_STATS_SCHEMA, lot_summary, write_runs_csv
    from eol_cal.records.connect import db_label

    keys = [q.key for q in QUANTITIES]
    for key in judged:
        if key not in keys:
            raise InputError(None, "--quantity", f"{key!r} is not one of {', '.join(keys)}")
    if judged and baseline_name is None:
        raise InputError(None, "--quantity", "judges against a baseline: give --baseline NAME")
    first, last = parse_date(since, "since"), parse_date(until, "until")
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
        t = Table(title="run rules against the baseline (Nelson 1, 2, 3, 5, 6)")
        for col in ("quantity", "variant", "station", "rule", "runs"):
            t.add_column(col)
        for v in doc["violations"]:
            t.add_row(v["quantity"], v["variant"], v["station"], v["text"],
                      ", ".join(f"{s} {str(a)[:16]}" for s, a in zip(v["serials"], v["started_at"], strict=True)))
        console.print(t)
        unjudged = [j for j in doc["judged"] if j["reason"]]
        for j in unjudged:
            console.print(f"  not judged: {j['quantity']} {j['variant']} {j['station']}: {j['reason']}")
        console.print(f"{len(doc['violations'])} rule violation(s)" + (" (exit 1)" if doc["violations"] else ""))


@lot_group.command("baseline")
@click.option("--db", required=True, type=RECORDS_DB, help="Records database: a SQLite file or postgresql://user@host:port/db.")
@click.option("--name", required=True, help="The baseline's name (lot stats --baseline NAME).")
@click.option("--since", default=None, metavar="TIME",
              help="Only runs started at or after this instant: an ISO 8601 time with its offset "
                   "(2026-11-22T06:00+01:00, ...Z) or a UTC day YYYY-MM-DD (from its start).")
@click.option("--until", default=None, metavar="TIME",
              help="Only runs started before this instant (a UTC day YYYY-MM-DD: to its end).")
@click.option("--variant", default=None, help="Only this product variant.")
@click.option("--station", "stations", multiple=True, help="Only this station (repeat for several) [default: all].")
@kind_option("the runs the baseline is made of (simulated: a lot simulate's what-if lot, with --station sim:NAME).")
@min_n_option
@click.option("--replace", is_flag=True, help="Replace a baseline of that name.")
@click.option("--json", "as_json", is_flag=True, help="Print the stored baseline as JSON.")
@handle_errors
def baseline_cmd(db, name, since, until, variant, stations, kind, min_n, replace, as_json) -> None:
    """Freeze centre lines and control limits per quantity, variant and station from the runs of
    a period (instants, not only days), of one kind, of one or more stations, and store them in
    the database: later `lot stats --baseline NAME` judges new runs against them (docs/spc.md).
    Groups with fewer than --min-n runs get no limits, nor phases spread round the circle (the
    reason is stored); an amplitude's LCL stops at zero (said so)."""
    from cli.common import print_json
    from eol_cal.errors import InputError
    from eol_cal.lot.baseline import baseline_document, baseline_of_db, instant, store
    from eol_cal.lot.spc import DEFAULT_MIN_N
    from eol_cal.records.connect import db_label

    if kind == "all":
        raise InputError(None, "--kind", "a baseline is of one kind of runs (production, master, simulated...)")
    filters = dict(since=None if since is None else instant(since, "--since"),
                   until=None if until is None else instant(until, "--until", end=True),
                   variant=variant, stations=tuple(dict.fromkeys(stations)) or None, kind=kind)
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

    t = Table(title=f"baseline {name}: {b.runs} {kind} run(s), min n {min_n}")
    for col in ("quantity", "unit", "variant", "station", "n", "centre", "sigma", "LCL", "UCL"):
        t.add_column(col, justify="left" if col in ("quantity", "unit", "variant", "station") else "right")
    for line in doc["lines"]:
        figures = ([_fmt(line[k]) for k in ("center", "sigma", "lcl", "ucl")] if line["reason"] is None
                   else [line["reason"], "", "", ""])
        if line["note"]:
            figures[2] += " (0: natural zero)"
        t.add_row(line["quantity"], line["unit"], line["variant"], line["station"], str(line["n"]), *figures)
    console.print(t)
    console.print(f"stored in {db_label(db)} as {name!r}")


@lot_group.command("diff")
@click.option("--db", required=True, type=RECORDS_DB, help="Records database: a SQLite file or postgresql://user@host:port/db.")
@click.argument("results", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@kind_option("each serial's latest run of this kind is compared.")
@click.option("--lot", "lots", multiple=True, metavar="STATION",
              help="Compare two lots instead of a refit: give it twice (a simulated lot's station is sim:NAME).")
@click.option("--json", "as_json", is_flag=True, help="Print the changes as JSON.")
@handle_errors
def diff_cmd(db, results, kind, lots, as_json) -> None:
    """Which motors a refit (`eol-cal refit -o RESULTS`) judges otherwise than their latest recorded
    run: the refit's verdict and failed limits against the fit-stage checks the record carries
    (a refit makes no compensated capture: the ripple limits are not compared). With --lot A
    --lot B: two lots side by side (yield, capability, causes) and the motors whose verdict
    differs (two simulated lots: the same motor number is the same motor)."""
    from cli.common import print_json
    from eol_cal.errors import InputError

    if lots:
        if results:
            raise InputError(None, "--lot", "compare two lots or a refit's results, not both")
        return _compare(db, lots, kind, as_json)
    if not results:
        raise InputError(None, "RESULTS", "give a refit's results file(s), or two --lot")
    from eol_cal.lot.diff import LOT_DIFF_SCHEMA, verdict_changes
    from eol_cal.lot.refit import read_rows
    from eol_cal.records.query import query_records

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


def _compare(db, lots, kind, as_json) -> None:
    from rich.table import Table

    from cli.common import print_json
    from eol_cal.lot.compare import LOT_COMPARE_SCHEMA, SHOWN, compare_lots

    doc = compare_lots(db, lots, "simulated" if kind == "production" and all(s.startswith("sim:") for s in lots)
                       else kind)
    if as_json:
        print_json({"schema": LOT_COMPARE_SCHEMA, **doc})
        return
    a, b = doc["lots"]
    t = Table(title=f"{a['station']} against {b['station']}")
    for col in ("figure", a["station"], b["station"]):
        t.add_column(col, justify="left" if col == "figure" else "right")
    y = lambda x: "-" if x is None else f"{100 * x:.1f} %"  # noqa: E731
    t.add_row("runs", str(a["runs"]), str(b["runs"]))
    t.add_row("yield (pass / judged)", y(a["yield"]), y(b["yield"]))
    for key in SHOWN:
        qa, qb = a["quantities"].get(key), b["quantities"].get(key)
        if qa and qb:
            t.add_row(f"{key} median ({qa['unit']})", _fmt(qa["p50"]), _fmt(qb["p50"]))
            t.add_row(f"{key} Cpk", _fmt(qa["cpk"], 3), _fmt(qb["cpk"], 3))
    t.add_row("top cause", a["pareto"][0]["cause"] if a["pareto"] else "-", b["pareto"][0]["cause"] if b["pareto"] else "-")
    console.print(t)
    console.print(f"{len(doc['changes'])} of {doc['compared']} motor(s) judged otherwise; "
                  f"{doc['only_in_one']} in one lot only")
    if doc["changes"]:
        t = Table(title="motors judged otherwise")
        for col in ("motor", a["station"], b["station"], "now failing", "no longer failing"):
            t.add_column(col)
        for c in doc["changes"]:
            t.add_row(c["motor"], c["verdicts"][0], c["verdicts"][1], ", ".join(c["newly_failing"]) or "-",
                      ", ".join(c["no_longer_failing"]) or "-")
        console.print(t)


@lot_group.command("simulate")
@click.option("--motors", required=True, type=click.IntRange(1, 999_999), help="Motors in the lot.")
@click.option("--spread", default="default", show_default=True, metavar="NAME|FILE.toml",
              help="Production spread the motors are drawn from (eol_cal/spreads/, docs/plant.md).")
@click.option("--limits", "limits_file", required=True, type=click.Path(exists=True, dir_okay=False),
              help="Limits file the runs are judged by (and whose variant's estimator options the blocks carry).")
@click.option("--variant", default=None, help="Variant in the limits file.")
@click.option("--db", required=True, type=RECORDS_DB, help="Records database: a SQLite file or postgresql://user@host:port/db.")
@click.option("--lot", "lot_name", default="SIM", show_default=True,
              help="The lot's name: its runs' station is sim:NAME (lot stats --kind simulated --station sim:NAME), "
                   "its serials NAME-000001...; the same name continues a lot that was stopped.")
@click.option("--seed", type=int, default=0, show_default=True, help="Motor i is drawn with seed SEED + i.")
@click.option("--profile", default="eol-default", show_default=True, help="Calibration capture's test profile.")
@click.option("--bench", default="paper", show_default=True, metavar="NAME|FILE.toml", help="Dyno bench the fit divides out.")
@click.option("--batch", type=click.IntRange(1, 256), default=None,
              help="Motors per task (default 8; part of the lot's identity).")
@click.option("--scheduler", default=None, metavar="tcp://HOST:8786", help="A running Dask scheduler to use.")
@click.option("--workers", type=click.IntRange(1, 256), default=2, show_default=True,
              help="Worker processes of the local cluster (127.0.0.1) when no --scheduler is given.")
@click.option("--json", "as_json", is_flag=True, help="Print what was done as JSON.")
@handle_errors
@io_paths(inputs=("limits_file", "spread", "profile", "bench"), outputs=())
def simulate_cmd(motors, spread, limits_file, variant, db, lot_name, seed, profile, bench, batch, scheduler, workers,
                 as_json) -> None:
    """A what-if lot: MOTORS drawn from a production spread, each through the station's cycle (what
    eol-cal run does: pre-flight, prepare, calibration capture, fit, table, flash, compensated
    capture, verdict, report) on the plant and the ECU simulator in-process, recorded as runs of
    kind simulated (never in the production statistics unless asked:
    lot stats/report --kind simulated --station sim:NAME). Resumable: run it again to finish a lot
    that was stopped; no motor is recorded twice."""
    import contextlib

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from cli.common import CommandExit, err_console, print_json
    from cli.refit import cluster_client, scheduler_address
    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot.cluster import RefitWorkerSetup
    from eol_cal.sim.plant_instruments import plant_instruments
    from eol_cal.station.whatif import check_plan, recorded_runs, simulate_lot
    from eol_cal.station.whatif_plan import SIM_BATCH, LotPlan
    from eol_cal.records.connect import db_label

    plan = LotPlan(lot_name, spread, str(limits_file), variant, motors, seed, profile, "paper", bench,
                   batch or SIM_BATCH)
    check_plan(plan)
    if scheduler is not None:
        scheduler_address(scheduler)  # before the database is read
    before = len(recorded_runs(db, plan) & {plan.run_id(i) for i in range(motors)})
    cache_dir = default_cache_dir()
    t0 = __import__("time").perf_counter()
    with contextlib.ExitStack() as stack:
        client = cluster_client(stack, scheduler, workers)
        # every worker: the plant's and estimator's tick loops in one kernel, JAX's compile cache,
        # the fit imported (eol_cal.lot.cluster)
        client.register_plugin(RefitWorkerSetup(cache_dir))
        with Progress(TextColumn(f"lot {plan.name}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      console=err_console, transient=False, refresh_per_second=2) as bar:
            task = bar.add_task("simulate", total=motors, completed=before)
            out = simulate_lot(plan, db, client, plant_instruments, on_done=lambda n: bar.advance(task, n),
                               cache_dir=cache_dir)
    seconds = __import__("time").perf_counter() - t0
    doc = {"lot": plan.name, "station": plan.station, "db": db_label(db), "motors": motors,
           "recorded_before": out.recorded_before, "recorded_now": out.recorded_now,
           "failed_batches": [{"motors": [b[0], b[-1]], "error": e} for b, e in out.failed_batches],
           "seconds": round(seconds, 1)}
    if as_json:
        print_json({"schema": LOT_SIMULATE_SCHEMA, **doc})
    else:
        console.print(f"lot {plan.name}: {out.recorded_now} motor(s) simulated and recorded in {seconds:.0f} s, "
                      f"{out.recorded_before} recorded before; lot stats --db {db_label(db)} --kind simulated "
                      f"--station {plan.station}")
    for b, e in out.failed_batches:
        err_console.print(f"motors {b[0]}..{b[-1]} not simulated: {e}")
    if out.failed_batches:
        raise CommandExit(1)


#: the schema of ``lot simulate --json``
LOT_SIMULATE_SCHEMA = "eol-cal/lot-simulate/1"


COMMANDS = [lot_group]
