"""``eol-cal msa type1``: is the station's ripple measurement capable? (a master motor's runs)"""

from __future__ import annotations

import math
from pathlib import Path

import click

from cli.common import RECORDS_DB, CommandExit, console, handle_errors
from cli.lot import day_options, min_n_option
from cli.paths import io_paths


def parse_pairs(values: tuple[str, ...], option: str, positive: bool = False) -> dict[str, float]:
    """``KEY=VALUE`` options as a dict (display units); bad ones are refused naming the option."""
    from eol_cal.errors import InputError
    from eol_cal.msa.study import TYPE1_QUANTITIES

    out: dict[str, float] = {}
    for text in values:
        key, sep, value = text.partition("=")
        key = key.strip()
        if not sep or key not in TYPE1_QUANTITIES:
            raise InputError(None, option, f"{text!r}: expected KEY=VALUE with KEY one of {', '.join(TYPE1_QUANTITIES)}")
        try:
            x = float(value)
        except ValueError:
            raise InputError(None, option, f"{text!r}: {value!r} is not a number") from None
        if not math.isfinite(x) or (positive and x <= 0.0):
            raise InputError(None, option, f"{text!r}: expected a {'positive' if positive else 'finite'} number")
        if key in out:
            raise InputError(None, option, f"{key} given twice")
        out[key] = x
    return out


@click.group("msa")
def msa_group() -> None:
    """Measurement system analysis: the station's measurement proved on a master motor."""


@msa_group.command("type1")
@click.option("--db", required=True, type=RECORDS_DB, help="Records database: a SQLite file or postgresql://user@host:port/db.")
@click.option("--serial", required=True, help="The master motor's serial: its recorded runs are the study.")
@day_options
@click.option("--reference", "references", multiple=True, metavar="KEY=VALUE",
              help="Reference value x_ref of a quantity in its display unit (k6 mN*m/A, phase_k6 deg, c6 mN*m, "
                   "pp_before_pct / pp_after_pct %); repeat per quantity.")
@click.option("--reference-run", default=None, metavar="RUN_ID",
              help="Take x_ref from this recorded run (not counted in the study); --reference overrides per quantity.")
@click.option("--tolerance", "tolerances", multiple=True, metavar="KEY=T",
              help="Tolerance width T = USL - LSL in the display unit; default for k6 and the p-p figures: the "
                   "variant's upper limit - 0.")
@click.option("--sigmas", "l", default=4.0, show_default=True, type=click.FloatRange(min=1.0, max=10.0),
              help="Study variation in standard deviations: 4 (+-2 s, VDA 5 / Bosch) or 6 (+-3 s, Minitab).")
@min_n_option
@click.option("--json", "as_json", is_flag=True, help="Print the study as one JSON document.")
@click.option("-o", "--out", "out", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="Write the study's page (one self-contained HTML file).")
@click.option("--plots", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Write each quantity's run chart as PNG into this directory (type1-KEY.png).")
@handle_errors
@io_paths(outputs=("out",), output_dirs=("plots",), databases=("db",))
def type1_cmd(db, serial, since, until, references, reference_run, tolerances, l, min_n, as_json, out, plots) -> None:
    """Type-1 gauge study of k6, phase_k6, c6 and the p-p figures over the master's runs: bias,
    repeatability s, Cg = 0.2 T / (4 s) and Cgk = (0.1 T - |bias|) / (2 s) (docs/spc.md).
    Exit 1 unless every quantity with a tolerance is capable (Cg and Cgk >= 1.33)."""
    from cli.common import print_json
    from cli.lot import parse_date
    from eol_cal.errors import InputError
    from eol_cal.lot.spc import DEFAULT_MIN_N
    from eol_cal.msa.study import document, read_runs, reference_of_run, studies
    from eol_cal.records.connect import db_label

    min_n = DEFAULT_MIN_N if min_n is None else min_n
    refs = parse_pairs(references, "--reference")
    tols = parse_pairs(tolerances, "--tolerance", positive=True)
    first, last = parse_date(since, "since"), parse_date(until, "until")
    sources = {key: "given" for key in refs}
    if reference_run is not None:
        of_run = reference_of_run(read_runs(db, run_id=reference_run), reference_run, serial)
        sources = {**{key: f"run {reference_run}" for key in of_run}, **sources}
        refs = {**of_run, **refs}
    lot = read_runs(db, serial=serial, since=first and first.isoformat(), until=last and last.isoformat(),
                    exclude=reference_run)
    if len(lot) == 0:  # nothing to study is bad input, not an incapable gauge (exit 1)
        window = "" if first is None and last is None else f" from {since or 'the start'} until {until or 'now'}"
        raise InputError(None, "--serial", f"no master or production run of {serial!r} in {db_label(db)}{window}: "
                                           "no recorded runs of this serial to study")
    results = studies(lot, refs, tols, sources, l=l, min_n=min_n)
    doc = {**document(results, serial=serial, runs=lot, min_n=min_n), "db": db_label(db)}
    if out is not None:
        from eol_cal.msa.type1_page import write_page

        titles = [f"{rid}, {str(t)[:19].replace('T', ' ')}" for rid, t in zip(lot.run_id, lot.started_at, strict=True)]
        write_page(out, doc, results, title=db_label(db), run_titles=titles)
    written = []
    if plots is not None:
        from eol_cal.msa.type1_page import write_pngs

        written = write_pngs(results, plots)
    if as_json:
        print_json(doc)
    else:
        _print(doc)
        if out is not None:
            console.print(f"page: {out}")
        for p in written:
            console.print(f"plot: {p}")
    if not doc["capable"]:
        raise CommandExit(1)


def _print(doc: dict) -> None:
    from rich.table import Table

    def f(x, digits: int = 4) -> str:
        return "-" if x is None else f"{x:.{digits}g}"

    c = doc["convention"]
    console.print(f"{doc['db']}: type-1 study of {doc['serial']}, {doc['runs']} run(s); Cg = {c['cg']}, "
                  f"Cgk = {c['cgk']}, capable at {c['capable_at']}")
    t = Table(title="type-1 study")
    for col in ("quantity", "unit", "n", "x_ref", "mean", "s", "bias", "p", "T", "Cg", "Cgk", "capable"):
        t.add_column(col, justify="left" if col in ("quantity", "unit", "capable") else "right")
    for q in doc["quantities"]:
        t.add_row(q["title"], q["unit"], str(q["n"]), f(q["reference"]), f(q["mean"]), f(q["sd"], 3), f(q["bias"], 3),
                  f(q["p_value"], 3), f(q["tolerance"]),
                  f(q["cg"], 3) if q["cg"] is not None else q["cg_reason"],
                  f(q["cgk"], 3) if q["cgk"] is not None else q["cgk_reason"],
                  {True: "yes", False: "NO"}.get(q["capable"], "-"))
    console.print(t)
    console.print("capable" if doc["capable"] else "NOT shown capable (exit 1)")


COMMANDS = [msa_group]
