"""``eol-cal gate``: a station's master-gate rules in the records database (set, clear, show,
history) and which master run admitted a serial's runs (docs/records.md, "Which master run
admitted a motor")."""

from __future__ import annotations

import click

from cli.common import RECORDS_DB, console, handle_errors, print_json
from cli.msa import parse_pairs
from cli.paths import io_paths

GATE_SCHEMA = "eol-cal/gate/1"
ADMITTED_SCHEMA = "eol-cal/gate-admitted/1"


def _db_option(func):
    return click.option("--db", required=True, type=RECORDS_DB,
                        help="Records database: a SQLite file or postgresql://user@host:port/db.")(func)


def _who(func):
    func = click.option("--note", default=None, help="Why the rules change (kept with the change).")(func)
    return click.option("--by", "set_by", required=True, help="Who changes the rules (kept with the change).")(func)


@click.group("gate")
def gate_group() -> None:
    """The master gate of a station: its rules in the records database, each change a record."""


def _text(value: str, name: str, longest: int = 200) -> str:
    from eol_cal.errors import InputError

    value = value.strip()
    if not value or len(value) > longest or not value.isprintable():
        raise InputError(None, name, f"{value!r}: 1 to {longest} printable characters")
    return value


@gate_group.command("set")
@_db_option
@click.option("--station", required=True, help="The station id the rules are for (its runs' station).")
@click.option("--serial", required=True, help="The master motor's serial.")
@click.option("--reference", "references", multiple=True, required=True, metavar="KEY=VALUE",
              help="The master's reference value in its display unit (k6 mN*m/A, phase_k6 deg, c6 mN*m, "
                   "pp_before_pct / pp_after_pct %); repeat per quantity.")
@click.option("--tolerance", "tolerances", multiple=True, required=True, metavar="KEY=T",
              help="The allowed deviation +-T from each reference (same unit); one per reference.")
@click.option("--every-h", default=None, type=float, help="A master check every this many hours, or:")
@click.option("--shifts", default=None, metavar="HH:MM,...", help="One master check per shift (start times).")
@click.option("--timezone", default=None, help="IANA zone of the shift times [default: UTC].")
@_who
@click.option("--json", "as_json", is_flag=True, help="Print the change as JSON.")
@handle_errors
@io_paths(inputs=("db",))
def set_cmd(db, station, serial, references, tolerances, every_h, shifts, timezone, set_by, note, as_json) -> None:
    """Set (or change) a station's gate rules: recorded as the station's next change; from then on
    every production run of the station needs a passing master run judged against them."""
    from eol_cal.msa.master import master_settings
    from eol_cal.msa.rules import change

    values: dict[str, object] = {"master.serial": serial, "master.every_h": every_h, "master.shifts": shifts,
                                 "master.timezone": timezone}
    values.update({f"master.reference.{k}": v for k, v in parse_pairs(references, "--reference").items()})
    values.update({f"master.tolerance.{k}": v for k, v in parse_pairs(tolerances, "--tolerance", positive=True).items()})
    m = master_settings(values, lambda _key: None)  # type: ignore[arg-type,return-value] # options: no file to name
    assert m is not None  # --serial is required
    made = change(db, _text(station, "--station", 64), m, _text(set_by, "--by", 64),
                  None if note is None else _text(note, "--note"))
    _show([made], as_json, db)


@gate_group.command("clear")
@_db_option
@click.option("--station", required=True, help="The station id whose gate ends.")
@_who
@click.option("--json", "as_json", is_flag=True, help="Print the change as JSON.")
@handle_errors
@io_paths(inputs=("db",))
def clear_cmd(db, station, set_by, note, as_json) -> None:
    """End a station's gate (recorded as a change, with who and why: --note is required)."""
    from eol_cal.errors import InputError
    from eol_cal.msa.rules import change

    if note is None:
        raise InputError(None, "--note", "required: say why the station runs without a master gate")
    made = change(db, _text(station, "--station", 64), None, _text(set_by, "--by", 64), _text(note, "--note"))
    _show([made], as_json, db)


@gate_group.command("show")
@_db_option
@click.option("--station", required=True, help="The station id.")
@click.option("--json", "as_json", is_flag=True, help="Print the rules as JSON.")
@handle_errors
@io_paths(inputs=("db",))
def show_cmd(db, station, as_json) -> None:
    """The rules in force on a station (exit 1 when it has none)."""
    from cli.common import CommandExit
    from eol_cal.msa.rules import current

    cur = current(db, station)
    _show([] if cur is None else [cur], as_json, db)
    if cur is None or cur.master is None:
        if not as_json:
            console.print(f"station {station}: no master gate")
        raise CommandExit(1)


@gate_group.command("history")
@_db_option
@click.option("--station", default=None, help="Only this station [default: every station].")
@click.option("--json", "as_json", is_flag=True, help="Print the changes as JSON.")
@handle_errors
@io_paths(inputs=("db",))
def history_cmd(db, station, as_json) -> None:
    """Every change of the gate rules, oldest first."""
    from eol_cal.msa.rules import history

    _show(history(db, station), as_json, db)


def change_json(c) -> dict:
    from eol_cal.msa.rules import rules_document

    return {"station": c.station, "seq": c.seq, "set_at": c.set_at, "set_by": c.set_by, "note": c.note,
            "rules": None if c.master is None else rules_document(c.master)}


def _rules_text(r: dict) -> str:
    refs = ", ".join(f"{k} {v:g} +-{r['tolerance'][k]:g}" for k, v in r["reference"].items())
    period = f"every {r['every_h']:g} h" if r["every_h"] is not None else f"shifts {','.join(r['shifts'])} {r['timezone']}"
    return f"master {r['serial']}, {period}; {refs}"


def _show(changes: list, as_json: bool, db) -> None:
    from eol_cal.records.connect import db_label

    docs = [change_json(c) for c in changes]
    if as_json:
        print_json({"schema": GATE_SCHEMA, "db": db_label(db), "changes": docs})
        return
    for d in docs:
        what = "cleared: no gate" if d["rules"] is None else _rules_text(d["rules"])
        console.print(f"{d['station']} rules #{d['seq']} set {d['set_at']} by {d['set_by']}: {what}"
                      + (f" ({d['note']})" if d["note"] else ""), markup=False, highlight=False)


@gate_group.command("admitted")
@_db_option
@click.option("--serial", required=True, help="The motor whose runs are asked about.")
@click.option("--json", "as_json", is_flag=True, help="Print the answer as JSON.")
@handle_errors
@io_paths(inputs=("db",))
def admitted_cmd(db, serial, as_json) -> None:
    """Which master run, under which rules and references, admitted each run of a serial (from
    the run records: what the station recorded when it ran). Exit 1 when a production run of the
    serial went through no gate."""
    from cli.common import CommandExit
    from eol_cal.records.parts_json import gate_json
    from eol_cal.records.connect import db_label
    from eol_cal.records.query import query_records

    records = query_records(db, serial=serial, kind="all")
    rows = [{"run_id": r.run_id, "started_at": r.started_at, "kind": r.kind, "verdict": r.verdict,
             "station": r.station_name, "gate": gate_json(r.gate)} for r in records]
    ungated = [r for r in rows if r["kind"] == "production" and (r["gate"] is None or r["gate"]["master_run"] is None)]
    if as_json:
        print_json({"schema": ADMITTED_SCHEMA, "db": db_label(db), "serial": serial, "runs": rows})
    else:
        console.print(f"{db_label(db)}: {len(rows)} run(s) of {serial}", markup=False, highlight=False)
        for r in rows:
            head = f"{r['started_at']} {r['run_id'][:8]} {r['kind']} {r['verdict']} on {r['station']}"
            g = r["gate"]
            if g is None:
                console.print(f"{head}: no master gate recorded", markup=False, highlight=False)
                continue
            rules = f"rules #{g['seq']} of {g['station']} set {g['set_at']}" if g["seq"] else g["source"]
            console.print(f"{head}: {rules}: {_rules_text(g['rules'])}", markup=False, highlight=False)
            if g["master_run"]:
                console.print(f"  admitted by master run {g['master_run']} ({g['master_started_at']}, "
                              f"{g['master_verdict']})", markup=False, highlight=False)
            for c in g["checks"]:
                value = "not measured" if c["value"] is None else f"{c['value']:.4g}"
                console.print(f"  {c['quantity']} = {value} {c['unit']}, reference {c['reference']:g} "
                              f"+-{c['tolerance']:g}: {'pass' if c['passed'] else 'FAIL'}", markup=False,
                              highlight=False)
    if ungated:
        raise CommandExit(1)


COMMANDS = [gate_group]
