"""Hostile scenarios of the master gate, the database as data and the statistics (issue 36,
classes 2-4), declared as :mod:`eol_cal.sim.fuzz.scenarios` declares its own (a :class:`Scenario`:
files, one command of the real CLI, what must come of it) and judged the same way.

Kinds: ``gate`` (every rule value of `eol-cal gate set` that must be refused; stored gate rows
that do not pass as settings), ``database`` (records databases holding triggers and views, on
every reading and writing command; stored baseline lines that are not numbers; newer layouts)
and ``baseline`` (selections of `lot baseline` that must be refused: wall times, empty periods,
unknown kinds). Its ``BUILDERS`` are picked up by :func:`eol_cal.sim.fuzz.scenarios.all_builders`
(bench/bench_faults.py --section scenarios --kinds gate database baseline).
"""

from __future__ import annotations

import functools
import json
import sqlite3
import tempfile
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from eol_cal.sim.fuzz.scenarios import FIXTURES, Scenario, made_later
from eol_cal.lot.baseline import baseline_of_db, store
from eol_cal.records.record import RunRecord
from eol_cal.records.migrations import migrate
from eol_cal.records.write import insert_records

_SET = ["gate", "set", "--db", "{d}/records.sqlite", "--station", "EOL-1", "--by", "qe"]
_GOOD = {"--serial": "M-MASTER", "--reference": "k6=0.62", "--tolerance": "k6=0.05", "--every-h": "8"}
#: values of each `gate set` option that must be refused
BAD_VALUES: dict[str, tuple[str, ...]] = {
    "--serial": ("", " ", "M\x01", "X" * 17, "Ä-1", "M 1 "),
    "--reference": ("k6=nan", "k6=inf", "k6=-1", "k6=", "k6", "volts=1", "k6=1e400", "phase_k6=720", "k6=0x10"),
    "--tolerance": ("k6=0", "k6=-0.1", "k6=nan", "k6=inf", "phase_k6=200", "c6=0.1"),
    "--every-h": ("0", "-8", "nan", "inf", "1e9", "0.001"),
    "--shifts": ("25:00", "06:00,xx", "", "6"),
    "--timezone": ("Mars/Olympus", "../../etc/passwd", "UTC+25"),
    "--station": ("", " ", "E" * 65, "EOL\n1"),
    "--by": ("", "x" * 65),
}


@functools.cache
def _base_db(lot: int, baseline: bool) -> bytes:
    """A records database: ``lot`` production runs of the demo's record on EOL-1 and a baseline
    ``b`` of them. Built once per shape: the scenarios differ only in the statements run on a copy
    (building one costs a second; the suite collects them in every worker)."""
    doc = json.loads((FIXTURES / "run_record_demo.json").read_text())
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "r.sqlite"
        migrate(db)
        recs = []
        for i in range(lot):
            d = json.loads(json.dumps(doc))  # each run its own copy, with a spread in k6 and the phases
            d.update(run_id=uuid.uuid4().hex, serial=f"S-{i}", started_at=f"2026-11-02T08:{i:02d}:00.000+00:00",
                     station={**doc["station"], "id": "EOL-1"})
            for key, step in (("k6", 1e-5), ("phase_k6", 0.01), ("c6", 1e-5), ("phase_c6", 0.01)):
                d["fit"][key]["value"] += step * ((i * 7) % 5 - 2)
            recs.append(RunRecord.from_json(d))
        insert_records(db, recs)
        if baseline:
            store(db, baseline_of_db(db, "b", {}, min_n=2))
        return _checkpointed(db)


def _checkpointed(db: Path) -> bytes:
    with sqlite3.connect(db) as con:
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    return db.read_bytes()


def _db(*statements: str, lot: int = 0, baseline: bool = False) -> Callable[[], bytes]:
    """A records database (``lot`` production runs of the demo's record on EOL-1, a baseline
    ``b`` of them), then ``statements`` run on it: made when a scenario is laid out, once a process
    (a suite collects the scenarios by name in every worker)."""
    return made_later(_db_bytes, statements, lot, baseline)


def _db_bytes(statements: tuple[str, ...], lot: int, baseline: bool) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "r.sqlite"
        db.write_bytes(_base_db(lot, baseline))
        with sqlite3.connect(db) as con:
            for s in statements:
                con.execute(s)
        return _checkpointed(db)


def gate_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """Each bad value of each `gate set` option; stored gate rows that would not pass as settings."""
    full = {"--station": "EOL-1", "--by": "qe", **_GOOD}
    for option, values in BAD_VALUES.items():
        for value in values:
            args = dict(full)
            if option == "--shifts":
                args.pop("--every-h")
            args[option] = value
            yield Scenario("gate", f"gate set {option} {value!r:.30}", {},
                           ["gate", "set", "--db", "{d}/records.sqlite", *(x for kv in args.items() for x in kv)])
    good = ('{"serial": "M-MASTER", "reference": {"k6": 0.62}, "tolerance": {"k6": 0.05}, "every_h": 8, '
            '"shifts": null, "timezone": "UTC"}')
    rows = {"tolerance 0": good.replace('"k6": 0.05', '"k6": 0'), "reference text": good.replace('0.62', '"x"'),
            "not json": "{", "a list": "[]", "unknown key": good.replace('"timezone"', '"volts": 1, "timezone"'),
            "NaN": good.replace("0.62", "NaN"), "no serial": good.replace('"M-MASTER"', "null"),
            "deep": "[" * 5000 + "]" * 5000}
    # a hostile file's table need not hold eol-cal's constraints: made anew without them
    create = ("DROP TABLE gate_rules", "CREATE TABLE gate_rules (station TEXT, seq INTEGER, set_at TEXT, set_by TEXT, "
              "action TEXT, rules_json TEXT, note TEXT, tool_version TEXT, PRIMARY KEY (station, seq))")
    for name, text in rows.items():
        row = (f"INSERT INTO gate_rules VALUES ('EOL-1', 1, '2026-11-22T08:00:00.000+00:00', 'qe', 'set', '{text}', "
               "NULL, 'x')")
        data = _db(*create, row)
        yield Scenario("gate", f"stored gate row: {name}", {"records.sqlite": data},
                       ["gate", "show", "--db", "{d}/records.sqlite", "--station", "EOL-1"])
        yield Scenario("gate", f"stored gate row: {name}, run", {"records.sqlite": data, "ecu.key": b"00" * 16 + b"\n"},
                       ["run", "--station-id", "EOL-1", "--dyno", "127.0.0.1:1", "--interface", "virtual", "--channel",
                        "none", "--limits", str(FIXTURES / "limits.toml"), "--db", "{d}/records.sqlite", "--serial",
                        "M-1", "--key-file", "{d}/ecu.key", "--report-dir", "{d}/rep", "--spool-dir", "{d}/spool"],
                       expect="any", protect=("ecu.key",))  # exit 2, the refusal on stdout; its record goes in
    for name, stmt in (("action", "UPDATE gate_rules SET action = 'maybe'"),
                       ("set_at", "UPDATE gate_rules SET set_at = 'yesterday'")):
        row = (f"INSERT INTO gate_rules VALUES ('EOL-1', 1, '2026-11-22T08:00:00.000+00:00', 'qe', 'set', '{good}', "
               "NULL, 'x')")
        yield Scenario("gate", f"stored gate row: {name}", {"records.sqlite": _db(*create, row, stmt)},
                       ["gate", "history", "--db", "{d}/records.sqlite"])
    newer = _db("UPDATE schema_version SET version = 99")
    yield Scenario("gate", "records layout 99", {"records.sqlite": newer}, ["gate", "history", "--db", "{d}/records.sqlite"])


#: stored objects eol-cal never creates, each refused by every command that opens the database
FOREIGN = {
    "trigger on insert": "CREATE TRIGGER t AFTER INSERT ON runs BEGIN DELETE FROM runs; END",
    "trigger on update": "CREATE TRIGGER t BEFORE UPDATE ON runs BEGIN SELECT RAISE(ABORT, 'no'); END",
    "view": "CREATE VIEW v AS SELECT serial FROM runs",
    "view over a missing table": "CREATE VIEW v AS SELECT * FROM nowhere",
}
_READERS: dict[str, list[str]] = {
    "records": ["records", "--db", "{d}/records.sqlite"],
    "records --json": ["records", "--db", "{d}/records.sqlite", "--json"],
    "records migrate": ["records", "migrate", "--db", "{d}/records.sqlite"],
    "lot stats": ["lot", "stats", "--db", "{d}/records.sqlite"],
    "lot report": ["lot", "report", "--db", "{d}/records.sqlite", "-o", "{d}/lot.html"],
    "lot baseline": ["lot", "baseline", "--db", "{d}/records.sqlite", "--name", "x", "--min-n", "2"],
    "msa type1": ["msa", "type1", "--db", "{d}/records.sqlite", "--serial", "S-1"],
    "gate history": ["gate", "history", "--db", "{d}/records.sqlite"],
    "gate set": [*_SET, *(x for kv in _GOOD.items() for x in kv)],
    "gate admitted": ["gate", "admitted", "--db", "{d}/records.sqlite", "--serial", "S-1"],
}


def database_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """Every foreign object under every command; stored baseline lines that are not numbers; newer layouts."""
    for obj, stmt in FOREIGN.items():
        data = _db(stmt, lot=3)
        for name, args in _READERS.items():
            yield Scenario("database", f"{obj}: {name}", {"records.sqlite": data}, args)
    lines = {"sigma 0": "sigma = 0", "sigma text": "sigma = 'abc'", "centre text": "center = 'x'",
             "centre NaN": "center = 1e999 - 1e999", "sigma without centre": "center = NULL",
             "mr negative": "mr_center = -1", "n text": "n = 'many'", "n negative": "n = -1",
             "unknown quantity": "quantity = 'volts'", "phase not circular": "circular = 0",
             "reason missing": "center = NULL, sigma = NULL, mr_center = NULL, reason = NULL"}
    for name, change in lines.items():
        which = "phase_k6" if "phase" in name else "k6"
        data = _db(f"UPDATE baseline_lines SET {change} WHERE quantity = '{which}'", lot=30, baseline=True)
        for cmd in (["lot", "stats", "--db", "{d}/records.sqlite", "--baseline", "b"],
                    ["lot", "report", "--db", "{d}/records.sqlite", "--baseline", "b", "-o", "{d}/lot.html"]):
            yield Scenario("database", f"baseline line {name}: {cmd[1]}", {"records.sqlite": data}, cmd)
    heads = {"min_n text": "min_n = 'x'", "runs negative": "runs = -5", "stations not a list": "stations = '{}'",
             "created_at number": "created_at = 5"}
    for name, change in heads.items():
        yield Scenario("database", f"baseline {name}", {"records.sqlite": _db(f"UPDATE baselines SET {change}", lot=30,
                                                                               baseline=True)},
                       ["lot", "stats", "--db", "{d}/records.sqlite", "--baseline", "b"])
    yield Scenario("database", "baseline, records layout 7", {"records.sqlite": _db("UPDATE schema_version SET version = 7",
                                                                                    lot=30, baseline=True)},
                   ["lot", "stats", "--db", "{d}/records.sqlite", "--baseline", "b"])


def baseline_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """Selections `lot baseline` must refuse."""
    data = _db(lot=30)
    base = ["lot", "baseline", "--db", "{d}/records.sqlite", "--name", "b", "--min-n", "2"]
    for name, extra in {
        "wall time without offset": ["--since", "2026-11-02T08:00"], "not a time": ["--since", "yesterday"],
        "until before since": ["--since", "2026-11-03", "--until", "2026-11-01"],
        "empty period": ["--since", "2026-11-02T08:00Z", "--until", "2026-11-02T08:00Z"],
        "no runs of the kind": ["--kind", "master"], "every kind": ["--kind", "all"],
        "unknown station": ["--station", "EOL-9"], "too few runs": ["--min-n", "1000"],
        "name blank": ["--name", " "], "name control": ["--name", "b\x1b[2J"],
        "day 31 Nov": ["--until", "2026-11-31"], "offset 25 h": ["--since", "2026-11-02T08:00+25:00"],
    }.items():
        yield Scenario("baseline", name, {"records.sqlite": data}, [*base, *extra])


BUILDERS: dict[str, Callable[[Mapping[str, bytes]], Iterator[Scenario]]] = {
    "gate": gate_scenarios, "database": database_scenarios, "baseline": baseline_scenarios,
}
