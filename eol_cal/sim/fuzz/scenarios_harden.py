"""Hostile scenarios of issue 36 (hardening round 3), in the shape of :mod:`eol_cal.sim.fuzz.scenarios`:
each a set of files, one command of the real CLI in a child process, and what must come of it.

Kinds, one per class of the issue:

- ``dbfiles`` (class 1): an output over a records database or a file SQLite keeps beside it
  (``-wal``, ``-shm``, ``-journal``), existing or not, through every writing option, the settings
  and the demos' own files;
- ``selections`` (class 5): the lot page, the statistics, the records and the type-1 study of a
  database holding no run, one, only refusals, only the master's, simulated or restore runs;
- ``oemkey`` (class 6): an OEM seed-to-key function that exits, raises ``BaseException``, hangs,
  kills its process, returns text, nothing, an empty or a 200 MB key, on import or on the seed;
- ``dynoclear`` (class 7): ``dyno-clear`` given a bad address, map or answer, or no dyno;
- ``signals`` (class 8): SIGTERM, SIGHUP or SIGINT at a moment of a command's start or run;
- ``round3`` (class 9): ``lot simulate``'s scheduler, seed and spread, ``simulate``'s seed, paths
  no file can have, NaN in a capture's header under ``--json``, ``msa type1`` without runs or
  with another serial's reference, a fit result's ``created``.

Every scenario is judged as :func:`eol_cal.sim.fuzz.scenarios.run_scenario` judges: no traceback, no
hang, no crash, no protected file changed or created, and a ``refuse`` scenario (or one a signal
reached) ends with exit 2 and one ``error:`` line.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import sqlite3
import tempfile
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from eol_cal.sim.fuzz import hostile
from eol_cal.sim.fuzz.scenarios import (FIXTURES, RUN, FileData, Scenario, example_block_bytes, file_bytes, made_later,
                                        station_files, station_toml)
from eol_cal.records.record import RunRecord

_SQLITE_WAL = b"\x37\x7f\x06\x82" + bytes(28)  # a write-ahead log's header: what SQLite writes beside a database
_SQLITE_JOURNAL = b"\xd9\xd5\x05\xf9\x20\xa1\x63\xd7" + bytes(24)


def _records(kind: str) -> list:
    """Records of one selection (``none``, ``one``, ``refused``, ``master``, ``simulated``,
    ``restore``, ``mixed``): the demo's record and the refusal fixture, re-keyed."""
    good = RunRecord.from_json(json.loads((FIXTURES / "run_record_demo.json").read_text()))
    refusal = RunRecord.from_json(json.loads((FIXTURES / "run_record_v1_refusal.json").read_text()))

    def copy(rec: RunRecord, serial: str, k: int, kind: str | None = None) -> RunRecord:
        started = f"2026-11-22T1{k}:00:00.000+00:00"
        return dataclasses.replace(rec, run_id=uuid.uuid4().hex, serial=serial, started_at=started, ended_at=started,
                                   kind=kind or rec.kind)

    return {
        "none": [], "one": [copy(good, "M-1", 0)],
        "refused": [copy(refusal, f"M-{k}", k) for k in range(3)],
        "master": [copy(good, "MASTER", k, kind="master") for k in range(3)],
        "simulated": [copy(good, f"S-{k}", k, kind="simulated") for k in range(3)],
        "restore": [copy(good, "M-1", 0, kind="restore")],
        "mixed": [copy(good, "MASTER", 0, kind="master"), copy(refusal, "M-2", 1), copy(good, "S-1", 2, kind="simulated")],
    }[kind]


def _db(records: list) -> Callable[[], bytes]:
    """A records database (one file, its log checkpointed) holding ``records``, made when a scenario
    holding it is laid out (a suite collects the scenarios by name in every worker)."""
    return made_later(_db_bytes, records)


def _db_bytes(records: list) -> bytes:
    from eol_cal.records.migrations import migrate
    from eol_cal.records.write import insert_records

    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "r.sqlite"
        migrate(db)
        if records:
            insert_records(db, records)
        with sqlite3.connect(db) as con:
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        return db.read_bytes()


# ------------------------------------------------------------------------------------ class 1


def dbfile_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """No output lands on a records database or a file of it, by any route."""
    db = _db(_records("one"))
    files: dict[str, FileData] = {
        **station_files(), "r.sqlite": db, "o.sqlite": db, "o.sqlite-wal": _SQLITE_WAL, "o.sqlite-journal": _SQLITE_JOURNAL,
        "cap.csv": bases["csv"], "fit.json": file_bytes(FIXTURES / "fit_paper.json"), "block.bin": example_block_bytes(),
        "sub/keep": b""}
    with_db = {"records --plot": ["records", "--db", "{d}/r.sqlite", "--plot", "{v}"],
               "lot report -o": ["lot", "report", "--db", "{d}/r.sqlite", "-o", "{v}"],
               "lot stats --csv": ["lot", "stats", "--db", "{d}/r.sqlite", "--csv", "{v}"],
               "msa type1 -o": ["msa", "type1", "--db", "{d}/r.sqlite", "--serial", "M-1", "-o", "{v}"],
               "records --flush --plot": ["records", "--db", "{d}/r.sqlite", "--flush", "--spool-dir", "{d}/spool",
                                          "--plot", "{v}"]}
    for route, args in with_db.items():
        for victim in ("r.sqlite", "r.sqlite-wal", "r.sqlite-shm", "r.sqlite-journal", "sub/../r.sqlite"):
            yield Scenario("dbfiles", f"{route} {victim}", files, [a.replace("{v}", f"{{d}}/{victim}") for a in args],
                           protect=("r.sqlite", victim.removeprefix("sub/../")))
    any_output = {"analyze --plot": ["analyze", "{d}/cap.csv", "--plot", "{v}"],
                  "table -o": ["table", "{d}/fit.json", "-o", "{v}"],
                  "table --hex": ["table", "{d}/fit.json", "-o", "{d}/n.bin", "--hex", "{v}"],
                  "block hex -o": ["block", "hex", "{d}/block.bin", "--bank", "0", "-o", "{v}"],
                  "index --plot": ["index", "--plot", "{v}"],
                  "fit -o": ["fit", "{d}/cap.csv", "-o", "{v}", "--allow-untraced"],
                  "capture convert": ["capture", "convert", "{d}/cap.csv", "{v}"],
                  "simulate --plot": ["simulate", "-o", "{d}/s.csv", "--speed-rpm", "60", "--iq", "10", "--seconds",
                                      "0.1", "--plot", "{v}"]}
    for route, args in any_output.items():
        for victim in ("o.sqlite", "o.sqlite-wal", "o.sqlite-journal"):
            yield Scenario("dbfiles", f"{route} over another database's {victim}", files,
                           [a.replace("{v}", f"{{d}}/{victim}") for a in args], protect=("o.sqlite", victim))
    for victim in ("records.sqlite", "records.sqlite-wal", "records.sqlite-shm", "records.sqlite-journal"):
        yield Scenario("dbfiles", f"run --log-file settings' {victim}", files, [*RUN, "--log-file", f"{{d}}/{victim}"],
                       protect=("records.sqlite", victim))
        yield Scenario("dbfiles", f"station --lot settings' {victim}", files,
                       ["station", "--station", "{d}/station.toml", "--operator", "bob", "--lot", f"{{d}}/{victim}"],
                       stdin="q\n", protect=("records.sqlite", victim))
        yield Scenario("dbfiles", f"station --demo --lot D/{victim.replace('records', 'results')}", {"D/keep": b""},
                       ["station", "--demo", "--out", "{d}/D", "--operator", "bob", "--lot",
                        f"{{d}}/D/{victim.replace('records', 'results')}"], stdin="q\n",
                       protect=(f"D/{victim.replace('records', 'results')}", "D/results.sqlite"))
    for mine in ("lot.html", "limits.toml"):
        for command in (["demo", "--motors", "1"], ["station", "--demo", "--operator", "bob"]):
            yield Scenario("dbfiles", f"{command[0]} --db over its own {mine} (an existing database)", {f"D/{mine}": db},
                           [*command, "--out", "{d}/D", "--db", f"{{d}}/D/{mine}"], stdin="q\n")
    yield Scenario("dbfiles", "station --demo --db D/x.sqlite --lot D/x.sqlite-wal", {"D/keep": b""},
                   ["station", "--demo", "--out", "{d}/D", "--operator", "bob", "--db", "{d}/D/x.sqlite", "--lot",
                    "{d}/D/x.sqlite-wal"], stdin="q\n", protect=("D/x.sqlite", "D/x.sqlite-wal"))


# ------------------------------------------------------------------------------------ class 5

SELECTIONS = ("none", "one", "refused", "master", "simulated", "restore", "mixed")


def selection_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """Every page and statistic of every odd selection: 0, 1 or 2, never a traceback."""
    commands = {"lot report": ["lot", "report", "--db", "{d}/r.sqlite", "-o", "{d}/lot.html"],
                "lot report --kind all": ["lot", "report", "--db", "{d}/r.sqlite", "-o", "{d}/lot.html", "--kind", "all"],
                "lot stats": ["lot", "stats", "--db", "{d}/r.sqlite"],
                "lot stats --kind all --json": ["lot", "stats", "--db", "{d}/r.sqlite", "--kind", "all", "--json"],
                "lot stats --csv": ["lot", "stats", "--db", "{d}/r.sqlite", "--kind", "all", "--csv", "{d}/s.csv"],
                "records": ["records", "--db", "{d}/r.sqlite"],
                "records --json --plot": ["records", "--db", "{d}/r.sqlite", "--json", "--plot", "{d}/r.png"],
                "lot report --station": ["lot", "report", "--db", "{d}/r.sqlite", "-o", "{d}/lot.html", "--station",
                                         "EOL-1", "--kind", "all"],
                "msa type1": ["msa", "type1", "--db", "{d}/r.sqlite", "--serial", "MASTER", "-o", "{d}/msa.html"]}
    for selection in SELECTIONS:
        db = _db(_records(selection))
        for name, args in commands.items():
            yield Scenario("selections", f"{name} of {selection}", {"r.sqlite": db}, args, expect="any",
                           protect=("r.sqlite",))


# ------------------------------------------------------------------------------------ class 6

#: OEM seed-to-key functions that misbehave: name -> body (``seed``, ``secret`` given)
OEM_FUNCTIONS = {
    "sys.exit(1)": "sys.exit(1)", "sys.exit(0)": "sys.exit(0)", "sys.exit(text)": "sys.exit('bye')",
    "BaseException": "raise BaseException('x')", "KeyboardInterrupt": "raise KeyboardInterrupt",
    "GeneratorExit": "raise GeneratorExit", "os._exit(3)": "os._exit(3)", "SIGKILL itself": "os.kill(os.getpid(), 9)",
    "hangs": "time.sleep(3600)", "empty key": "return b''", "200 MB key": "return b'k' * 200_000_000",
    "65-byte key": "return b'k' * 65", "text": "return 'abcd'", "None": "return None", "int": "return 1234",
    "list of ints": "return [1, 2, 3, 4]", "recursion": "return f_recursion(seed, secret)",
    "memory": "return bytes(8 * 1024**3)", "prints a fake answer, then exits": "print('[\"key\", \"01020304\"]'); sys.exit(0)",
    "closes stdout": "os.close(1); return b'1234'",
}
OEM_MODULES = {"exits on import": "import sys\nsys.exit(2)\n", "raises on import": "raise BaseException('import')\n",
               "hangs on import": "import time\ntime.sleep(3600)\n", "not callable": "f = 3\n", "no function": "g = 1\n"}


def _oem_module() -> bytes:
    lines = ["import os, sys, time"]
    for k, body in enumerate(OEM_FUNCTIONS.values()):
        lines.append(f"def f{k}(seed, secret):\n    {body}")
    lines.append("def f_recursion(seed, secret):\n    return f_recursion(seed, secret)")
    return ("\n".join(lines) + "\n").encode()


def oemkey_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """Each misbehaving function through flash, ecu restore and run: refused with exit 2, bounded."""
    module = _oem_module()
    specs = {name: f"oem_evil:f{k}" for k, name in enumerate(OEM_FUNCTIONS)}
    specs.update({name: f"oem_{k}:f" for k, name in enumerate(OEM_MODULES)})
    extra = {f"oem_{k}.py": body.encode() for k, body in enumerate(OEM_MODULES.values())}
    for name, spec in specs.items():
        files = {**station_files(key_algo=f'"{spec}"'), "oem_evil.py": module, **extra, "block.bin": example_block_bytes()}
        yield Scenario("oemkey", f"flash: {name}", files,
                       ["flash", "{d}/block.bin", "-i", "virtual", "-c", "nobody", "--key-algo", spec])
        yield Scenario("oemkey", f"ecu restore: {name}", files,
                       ["ecu", "restore", "--bank", "previous", "-i", "virtual", "-c", "nobody", "--key-algo", spec,
                        "--save", "{d}/saved.bin"])
        if "hangs" not in name:  # a hang is bounded the same way everywhere: once per command is enough
            # one that returns a key after closing its stdout is an odd but working algorithm: the run
            # goes on to its pre-flight (no dyno here: a refusal of the motor, not of the input)
            yield Scenario("oemkey", f"run (settings key_algo): {name}", files, RUN,
                           expect="any" if name == "closes stdout" else "refuse")


# ------------------------------------------------------------------------------------ class 7


def dynoclear_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """dyno-clear refuses what it cannot do: one line, exit 2, nothing written."""
    for address in ("a b", "http://127.0.0.1:1", "127.0.0.1:99999", "[zz]:502", "", "127.0.0.1:1"):
        for answer in ("yes\n", "no\n"):
            yield Scenario("dynoclear", f"--dyno {address!r}, answer {answer.strip()}", {},
                           ["dyno-clear", "--dyno", address, "--timeout", "0.2"], stdin=answer)
    maps = {"missing": None, "garbage": b"\x00[[[\n", "a FIFO": None, "no fault_reset": b'name = "x"\n'}
    for name, data in maps.items():
        files = {} if name == "missing" else {"map.toml": data}
        yield Scenario("dynoclear", f"--register-map {name}", files,
                       ["dyno-clear", "--dyno", "127.0.0.1:1", "--register-map", "{d}/map.toml", "--yes"])
    yield Scenario("dynoclear", "--timeout 0", {}, ["dyno-clear", "--dyno", "127.0.0.1:1", "--timeout", "0"])


# ------------------------------------------------------------------------------------ class 8

SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)
#: the address-space limit of a signalled command: a station cycle (JAX, XLA, both simulators) aborts
#: under the campaign's 2 GiB whether signalled or not (std::bad_alloc); these scenarios are about signals
SIGNALS_MEMORY_BYTES = 16 * 1024**3
SIGNAL_AT_S = (0.2, 0.5, 1.0, 2.0)


def signal_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """A signal at a moment of a command's start or run: exit 2 (never 130/143/129, never 0)."""
    files: dict[str, FileData] = {**station_files(), "r.sqlite": _db(_records("mixed")), "cap.csv": bases["csv"],
                                  "fit.json": file_bytes(FIXTURES / "fit_paper.json")}
    commands = {"run": RUN, "records": ["records", "--db", "{d}/r.sqlite"],
                "lot report": ["lot", "report", "--db", "{d}/r.sqlite", "-o", "{d}/lot.html", "--kind", "all"],
                "analyze": ["analyze", "{d}/cap.csv"], "table": ["table", "{d}/fit.json", "-o", "{d}/b.bin"],
                "capture info": ["capture", "info", "{d}/cap.csv"],
                "simulate": ["simulate", "-o", "{d}/s.csv", "--speed-rpm", "60", "--iq", "10", "--seconds", "0.2"],
                "station --demo": ["station", "--demo", "--out", "{d}/D", "--operator", "bob"],
                "demo": ["demo", "--motors", "1", "--out", "{d}/D"]}
    for name, args in commands.items():
        for sig in SIGNALS:
            if name == "station --demo" and sig == signal.SIGINT:
                continue  # Ctrl-C at the station's prompt is the operator ending the session: exit 0, documented
            for at in SIGNAL_AT_S:
                yield Scenario("signals", f"{name}: {sig.name} at {at:g} s", files, args, expect="any",
                               stdin="DEMO-0001\nq\n" if name == "station --demo" else "", signal_at=(int(sig), at),
                               protect=("r.sqlite", "station.toml", "limits.toml", "ecu.key", "cap.csv", "fit.json"),
                               memory_bytes=SIGNALS_MEMORY_BYTES, env={"PYTHONFAULTHANDLER": "1"})


# ------------------------------------------------------------------------------------ class 9


def _base_mdf4_header(bases: Mapping[str, bytes], key: str, value: str) -> bytes:
    """The base MDF4 capture with its header's ``key`` set to ``value`` (text)."""
    return _mdf4_header(bases["mdf4"], key, value)


def _mdf4_header(base: bytes, key: str, value: str) -> bytes:
    xml = hostile.check_mdf4_bytes(base).header_comment
    start = xml.index(f'<e name="{key}">') + len(f'<e name="{key}">')
    return hostile.mdf4_with_header_comment(base, xml[:start] + value + xml[xml.index("</e>", start):])


def round3_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """The rest of the list: refused with exit 2 before anything runs, one line."""
    limits = file_bytes(FIXTURES / "limits.toml")
    lot = ["lot", "simulate", "--motors", "2", "--limits", "{d}/limits.toml", "--db", "{d}/r.sqlite"]
    spreads = {"empty": b"", "names only": b'name = "x"\n',
               "negative sigma": b'[k6]\ndist = "normal"\nmean = 6e-4\nsigma = -1e-5\n',
               "NaN mean": b'[c6]\ndist = "normal"\nmean = nan\nsigma = 1e-4\n', "unknown key": b"[k7]\ndist = \"phase\"\n"}
    for name, extra in ({f"--scheduler {s!r}": ["--scheduler", s] for s in ("not a url", "http://127.0.0.1:1", "tcp://",
                                                                              "tcp://127.0.0.1:99999", ":8786", "tcp://[zz]:1")}
                        | {f"--seed {s}": ["--seed", s] for s in ("-1", str(2**63), str(2**63 - 2), str(2**70), "-99999")}
                        | {f"--spread {s}": ["--spread", "{d}/spread.toml"] for s in spreads}).items():
        data = spreads.get(name.removeprefix("--spread "), b"")
        yield Scenario("round3", f"lot simulate {name}", {"limits.toml": limits, "spread.toml": data}, [*lot, *extra])
    for seed in ("-1", str(2**63), str(2**64)):
        yield Scenario("round3", f"simulate --seed {seed}", {},
                       ["simulate", "-o", "{d}/s.csv", "--seed", seed, "--seconds", "0.1"])
    bad_paths = {"NUL": '"x\\u0000y"', "5000 characters": '"' + "p" * 5000 + '"', "a 300-byte name": '"' + "n" * 300 + '"',
                 "4100 characters of directories": '"' + "d/" * 2050 + 'x"'}
    for key in ("db", "report_dir", "spool_dir", "key_file", "limits"):
        for name, value in bad_paths.items():
            yield Scenario("round3", f"settings {key} {name}", station_files(**{key: value}), RUN)
    yield Scenario("round3", "settings report_dir /proc/self", station_files(report_dir='"/proc/self"'), RUN)
    # the spool is where a record waits when the database fails: one it cannot take is no refusal (by design)
    yield Scenario("round3", "settings spool_dir /proc/self", station_files(spool_dir='"/proc/self"'), RUN, expect="any")
    for command in (["records"], ["lot", "stats"], ["lot", "report", "-o", "{d}/l.html"], ["records", "migrate"],
                    ["msa", "type1", "--serial", "M"]):
        yield Scenario("round3", f"{' '.join(command[:2])} --db of 5000 characters", {}, [*command, "--db", "x" * 5000])
    for key in ("kt", "poles", "encoder_ppr"):
        for value in ("nan", "inf", "-inf", "1e999"):
            yield Scenario("round3", f"capture info --json, MDF4 header {key} = {value}",
                           {"c.mf4": made_later(_base_mdf4_header, bases, key, value)},
                           ["capture", "info", "--json", "{d}/c.mf4"])
    for value in ("nan", "inf"):
        yield Scenario("round3", f"capture info --json, CSV kt = {value}",
                       {"c.csv": hostile.csv_with_meta_line(bases["csv"], f"# kt: {value}")},
                       ["capture", "info", "--json", "{d}/c.csv"], expect="any")
    db = _db(_records("mixed"))
    yield Scenario("round3", "msa type1 of a serial without runs", {"r.sqlite": db},
                   ["msa", "type1", "--db", "{d}/r.sqlite", "--serial", "NOBODY"])
    yield Scenario("round3", "msa type1 of a window without runs", {"r.sqlite": db},
                   ["msa", "type1", "--db", "{d}/r.sqlite", "--serial", "MASTER", "--since", "2030-01-01"])
    yield Scenario("round3", "msa type1 --reference-run of no run", {"r.sqlite": db},
                   ["msa", "type1", "--db", "{d}/r.sqlite", "--serial", "MASTER", "--reference-run", "f" * 32])
    fit = json.loads(file_bytes(FIXTURES / "fit_paper.json"))
    for created in ("yesterday", "2026-11-24T00:23:36", 20261124, "", "1969-12-31T23:59:59+00:00",
                    "2106-02-07T06:28:16+00:00", ["2026"], "2026-13-01T00:00:00+00:00"):
        doc = dict(fit, created=created)
        yield Scenario("round3", f"table, created = {created!r}", {"fit.json": json.dumps(doc).encode()},
                       ["table", "{d}/fit.json", "-o", "{d}/b.bin"])
    # another serial's run as the reference: its run id is only known once the database is made
    for name, records in (("another serial's", _records("mixed")),):
        ref = next(r for r in records if r.serial != "MASTER")
        yield Scenario("round3", f"msa type1 --reference-run of {name}", {"r.sqlite": _db(records)},
                       ["msa", "type1", "--db", "{d}/r.sqlite", "--serial", "MASTER", "--reference-run", ref.run_id])
    yield Scenario("round3", "run settings of a station without a dyno map key", {**station_files(), "st2.toml":
                   station_toml(db='"r.sqlite"').replace(b"[dyno]\n", b"[dyno]\nregister_map = \"\\u0000\"\n")},
                   ["run", "--station", "{d}/st2.toml", "--serial", "M-1"])


#: kind -> builder(bases) of its scenarios (picked up by eol_cal.sim.fuzz.scenarios.all_builders)
BUILDERS: dict[str, Callable[[Mapping[str, bytes]], Iterator[Scenario]]] = {
    "dbfiles": dbfile_scenarios, "selections": selection_scenarios, "oemkey": oemkey_scenarios,
    "dynoclear": dynoclear_scenarios, "signals": signal_scenarios, "round3": round3_scenarios,
}
