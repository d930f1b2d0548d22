"""Targeted fault scenarios (issue 23): each one a set of files, one command of the real CLI, and
what the tool must do with it, run in a child process like the mutation campaign
(:mod:`eol_cal.sim.fuzz.campaign`).

Kinds: ``toml`` (every TOML file the tool reads, with numbers of thousands of digits, nesting
thousands deep, oversized, a FIFO), ``json`` (fit results, refit rows, spool files, stored
records with NaN), ``csv`` and ``mdf4`` (header cells that made a parser backtrack, record counts
and flags a decoder believed, duplicate header keys, a complex channel), ``paths`` (an output
over an input through every writing option, setting and default), ``refusals`` (settings values,
serials and ECU-state records that must be refused) and ``exits`` (bad input to ``refit``).

A scenario ``expect`` is ``"refuse"`` (exit 2, the refusal on one line) or ``"any"`` (0, 1 or 2:
a file that may well be valid). Every scenario is judged as the campaign judges: no traceback, no
hang, no crash (a signal, another exit code, a MemoryError), no input modified; and a ``refuse``
scenario that ends 0 or 1 is an input accepted that should have been refused.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import json
import os
import pkgutil
import shutil
import sqlite3
import tempfile
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import eol_cal.sim.fuzz as fuzz_package
from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.ecu import protocol as P
from eol_cal.firmware.example import example_block
from eol_cal.infra.inputs import MAX_TOML_BYTES
from eol_cal.sim import FIXTURES, ROOT
from eol_cal.sim.fuzz import hostile
from eol_cal.sim.fuzz.campaign import CHILD_MEMORY_BYTES, Counts, run_cli
from eol_cal.sim.fuzz.mutate import fit_result_with_mech
from eol_cal.records.limits import LIMITS
from eol_cal.records.record import RunRecord
from eol_cal.records.write import insert_records


#: a scenario's file: its bytes, a function that makes them when it is laid out, or None (a FIFO)
FileData = bytes | Callable[[], bytes] | None


def made_later(make: Callable[..., bytes], *args: Any) -> Callable[[], bytes]:
    """``make(*args)`` as a scenario's file: made when a scenario holding it is first laid out, then kept."""
    return functools.cache(functools.partial(make, *args))


@dataclass
class Scenario:
    """Files to lay out in an empty directory, one command, and what must come of it.

    ``files`` maps a relative name to bytes, to a function that makes them when the scenario is
    laid out (a database, an MDF4 capture: a test suite collects every scenario by its name in every
    worker, and runs each once), or to ``None`` for a FIFO. ``args`` may use ``{d}`` for the
    scenario's directory. ``protect`` names the files that must not change (default: all of them).
    """

    kind: str
    name: str
    files: Mapping[str, FileData]
    args: list[str]
    expect: str = "refuse"
    env: dict[str, str] = field(default_factory=dict)
    stdin: str = ""
    protect: tuple[str, ...] | None = None
    #: (signal, seconds after the start): a signal that comes while the command runs must end it with exit 2
    signal_at: tuple[int, float] | None = None
    #: the child's address-space limit (default CHILD_MEMORY_BYTES; a whole station cycle with JAX needs more)
    memory_bytes: int | None = None

    def lay_out(self, d: Path) -> None:
        d.mkdir(parents=True, exist_ok=True)
        for rel, data in self.files.items():
            path = d / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            if data is None:
                os.mkfifo(path)
            else:
                path.write_bytes(data() if callable(data) else data)

    def digests(self, d: Path) -> dict[str, str]:
        names = self.protect if self.protect is not None else tuple(k for k, v in self.files.items() if v is not None)
        return {n: hashlib.sha256((d / n).read_bytes()).hexdigest() if (d / n).is_file() else "-" for n in names}

    def argv(self, d: Path) -> list[str]:
        return [a.format(d=d) for a in self.args]


# ------------------------------------------------------------------------------------ the files


def file_bytes(path: Path) -> bytes:
    """The bytes of a fixture file (a scenario's input as it is)."""
    return path.read_bytes()


def _key() -> bytes:

    return (P.DEV_SECRET.hex() + "\n").encode()


def station_toml(**keys: str) -> bytes:
    """A station settings file with these keys (TOML values as text) over a valid default."""
    values = {"station_id": '"L3"', "limits": '"limits.toml"', "db": '"records.sqlite"', "key_file": '"ecu.key"',
              "report_dir": '"reports"', "spool_dir": '"spool"', **keys}
    body = "".join(f"{k} = {v}\n" for k, v in values.items())
    return (body + '[dyno]\naddress = "127.0.0.1:1"\n[can]\ninterface = "virtual"\nchannel = "nobody"\n').encode()


def station_files(**keys: str) -> dict[str, bytes]:
    """A station directory whose dyno and bus go nowhere: every scenario here ends before them."""
    return {"station.toml": station_toml(**keys), "ecu.key": _key(), "limits.toml": file_bytes(FIXTURES / "limits.toml")}


RUN = ["run", "--station", "{d}/station.toml", "--serial", "M-1"]
_TOML_SOURCES = {
    "limits": FIXTURES / "limits.toml", "motor": None, "bench": ROOT / "eol_cal" / "benches" / "paper.toml",
    "profile": ROOT / "eol_cal" / "profiles" / "paper.toml", "register_map": ROOT / "eol_cal" / "dyno" / "maps" / "default.toml",
    "map": FIXTURES / "daq_export_foreign.map.toml", "settings": None,
}


def _toml_scenario(kind: str, name: str, data: bytes | None) -> Scenario:
    target = f"hostile-{kind}.toml"
    if kind == "map":
        return Scenario("toml", f"{kind}: {name}", {target: data, "daq.csv": file_bytes(FIXTURES / "daq_export_foreign.csv")},
                        ["capture", "info", "--map", f"{{d}}/{target}", "{d}/daq.csv"])
    if kind == "settings":
        files = {**station_files(), target: data}
        return Scenario("toml", f"{kind}: {name}", files, ["run", "--station", f"{{d}}/{target}", "--serial", "M-1"])
    station = station_files()
    if kind == "register_map":
        station["station.toml"] = station["station.toml"].replace(b"[dyno]\n", f'[dyno]\nregister_map = "{target}"\n'.encode())
    else:
        station["station.toml"] = station_toml(**{kind: f'"{target}"'})
    return Scenario("toml", f"{kind}: {name}", {**station, target: data}, RUN)


def toml_scenarios() -> Iterator[Scenario]:
    """Every TOML kind with every hostile line, an oversized file and a FIFO."""

    for kind, source in _TOML_SOURCES.items():
        if kind == "motor":
            valid = b"poles = 6\n"
        elif kind == "settings":
            valid = station_toml()
        else:
            assert source is not None  # only the motor and the settings have no source file
            valid = file_bytes(source)
        for name, line in hostile.TOML_LINES.items():
            yield _toml_scenario(kind, name, (line + "\n").encode() + valid)
        yield _toml_scenario(kind, f"{MAX_TOML_BYTES + 1024} bytes", b"#" * (MAX_TOML_BYTES + 1023) + b"\n" + valid)
        yield _toml_scenario(kind, "a FIFO", None)


def json_scenarios() -> Iterator[Scenario]:
    """Fit results with hostile numbers and nesting, refit rows, spool files, a stored record with NaN."""
    fit = json.loads((FIXTURES / "fit_paper.json").read_text())
    for name, token in hostile.JSON_TOKENS.items():
        doc = json.loads(json.dumps(fit))
        doc["motors"][0]["k6"]["value"] = "@@"
        data = json.dumps(doc).replace('"@@"', token).encode()
        yield Scenario("json", f"fit result: {name}", {"fit.json": data}, ["table", "{d}/fit.json", "-o", "{d}/b.bin"])
        yield Scenario("json", f"refit row: {name}", {"rows.jsonl": f'{{"serial": "M-1", "k6": {token}}}\n'.encode(),
                                                       "records.sqlite": _records_db},
                       ["lot", "diff", "--db", "{d}/records.sqlite", "{d}/rows.jsonl"])
        yield Scenario("json", f"spool file: {name}", {"spool/x.json": f'{{"schema": {token}}}'.encode(),
                                                        "records.sqlite": _records_db},
                       ["records", "--db", "{d}/records.sqlite", "--flush", "--spool-dir", "{d}/spool"], expect="any")
    yield Scenario("json", "spool file: a FIFO", {"spool/x.json": None, "records.sqlite": _records_db},
                   ["records", "--db", "{d}/records.sqlite", "--flush", "--spool-dir", "{d}/spool"], expect="any")
    for name, token in (("NaN", "NaN"), ("Infinity", "Infinity"), ("arrays 100000 deep", "[" * 100000 + "]" * 100000)):
        yield Scenario("json", f"stored record: {name}", {"records.sqlite": functools.partial(_records_db, token)},
                       ["records", "--db", "{d}/records.sqlite", "--json"], expect="any")


@functools.cache
def _records_db(token: str | None = None) -> bytes:
    """A records database of one run (its record JSON holding ``token`` in a value); a scenario
    names it (``functools.partial(_records_db, token)``) and gets it made when laid out."""

    rec = json.loads((FIXTURES / "run_record_demo.json").read_text())
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "r.sqlite"
        insert_records(db, [RunRecord.from_json(rec)])
        if token is not None:
            with sqlite3.connect(db) as con:
                doc = json.loads(con.execute("SELECT record_json FROM runs").fetchone()[0])
                doc["metrics"] = {"pp_before_pct": "@@"}
                con.execute("UPDATE runs SET record_json = ?", (json.dumps(doc).replace('"@@"', token),))
            with sqlite3.connect(db) as con:
                con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        return db.read_bytes()


def capture_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """CSV header cells and metadata lines; MDF4 record counts, flags, header comments."""
    for name, cell in hostile.CSV_HEADER_CELLS.items():
        yield Scenario("csv", f"header cell {name}", {"c.csv": hostile.csv_with_header_cell(bases["csv"], cell)},
                       ["capture", "info", "{d}/c.csv"], expect="any")
    for name, line in hostile.CSV_META_LINES.items():
        yield Scenario("csv", f"metadata {name}", {"c.csv": hostile.csv_with_meta_line(bases["csv"], line)},
                       ["capture", "info", "{d}/c.csv"], expect="any")
    for fld, values in hostile.MDF4_CG_FIELDS.items():
        for value in values:
            yield Scenario("mdf4", f"channel group {fld} = {value}",
                           {"c.mf4": hostile.mdf4_with_cg_field(bases["mdf4"], fld, value)}, ["capture", "info", "{d}/c.mf4"])
    for name, extra, where in hostile.MDF4_COMMENTS:
        data = hostile.mdf4_with_header_comment(bases["mdf4"], hostile.header_comment_with(bases["mdf4"], extra, where))
        yield Scenario("mdf4", f"header comment: {name}", {"c.mf4": data}, ["capture", "info", "--json", "{d}/c.mf4"],
                       expect="any" if "nested" in name else "refuse")


def example_block_bytes() -> bytes:
    """A valid parameter block (the firmware's example, serial M-0007)."""
    return example_block(serial="M-0007")


def path_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """An output over an input through every writing option, setting and default."""
    st: dict[str, FileData] = {
        **station_files(), "block.bin": example_block_bytes(), "can.ini": b"[default]\ninterface = virtual\nchannel = x\n",
        "motor.toml": b"poles = 6\n", "profile.toml": file_bytes(ROOT / "eol_cal" / "profiles" / "paper.toml"),
        "cap.csv": bases["csv"], "fit.json": file_bytes(FIXTURES / "fit_paper.json"), "records.sqlite": _records_db}
    flash = ["flash", "{d}/block.bin", "--can-config", "{d}/can.ini", "--key-file", "{d}/ecu.key", "--motor", "{d}/motor.toml"]
    for victim in ("block.bin", "ecu.key", "can.ini", "motor.toml"):
        yield Scenario("paths", f"flash --log-file {victim}", st, [*flash, "--log-file", f"{{d}}/{victim}"])
    yield Scenario("paths", "ecu restore --save key file", st, ["ecu", "restore", "--from", "{d}/block.bin", "-i", "virtual",
                                                                 "-c", "x", "--key-file", "{d}/ecu.key", "--save", "{d}/ecu.key"])
    yield Scenario("paths", "acquire --log-file profile", st,
                   ["acquire", "--dyno", "127.0.0.1:1", "--profile", "{d}/profile.toml", "-o", "{d}/new.mf4",
                    "--log-file", "{d}/profile.toml"])
    yield Scenario("paths", "acquire --log-file = -o", st, ["acquire", "--dyno", "127.0.0.1:1", "-o", "{d}/cap.csv",
                                                             "--log-file", "{d}/cap.csv"])
    for victim in ("station.toml", "limits.toml", "ecu.key"):
        yield Scenario("paths", f"run --log-file {victim}", st, [*RUN, "--log-file", f"{{d}}/{victim}"])
    for victim in ("ecu.key", "limits.toml", "station.toml"):
        files = {**st, "station.toml": station_toml(db=f'"{victim}"')}
        yield Scenario("paths", f"settings db = {victim}", files, RUN)
        yield Scenario("paths", f"station settings db = {victim}", files,
                       ["station", "--station", "{d}/station.toml", "--operator", "bob"], stdin="q\n")
    for victim in ("records.sqlite", "limits.toml", "station.toml", "ecu.key"):
        yield Scenario("paths", f"station --lot {victim}", st, ["station", "--station", "{d}/station.toml", "--operator",
                                                                 "bob", "--lot", f"{{d}}/{victim}"], stdin="q\n")
    yield Scenario("paths", "fit -o capture", st, ["fit", "{d}/cap.csv", "-o", "{d}/cap.csv", "--allow-untraced"])
    yield Scenario("paths", "analyze --plot capture", st, ["analyze", "{d}/cap.csv", "--plot", "{d}/cap.csv"])
    yield Scenario("paths", "table -o fit result", st, ["table", "{d}/fit.json", "-o", "{d}/fit.json"])
    yield Scenario("paths", "table --hex fit result", st, ["table", "{d}/fit.json", "-o", "{d}/n.bin", "--hex", "{d}/fit.json"])
    yield Scenario("paths", "capture convert over itself", st, ["capture", "convert", "{d}/cap.csv", "{d}/cap.csv"])
    yield Scenario("paths", "block hex -o block", st, ["block", "hex", "{d}/block.bin", "--bank", "0", "-o", "{d}/block.bin"])
    yield Scenario("paths", "records --plot database", st, ["records", "--db", "{d}/records.sqlite", "--plot",
                                                             "{d}/records.sqlite"])
    yield Scenario("paths", "lot report -o database", st, ["lot", "report", "--db", "{d}/records.sqlite", "-o",
                                                            "{d}/records.sqlite"])
    yield Scenario("paths", "lot stats --csv database", st, ["lot", "stats", "--db", "{d}/records.sqlite", "--csv",
                                                              "{d}/records.sqlite"])
    yield Scenario("paths", "refit -o capture", st, ["refit", "{d}/cap.csv", "-o", "{d}/cap.csv"])
    sim_dir = {"lot/SIM-000001.csv": example_block_bytes()}
    yield Scenario("paths", "simulate --out-dir over its --block (named at run time)", sim_dir,
                   ["simulate", "--motors", "2", "--out-dir", "{d}/lot", "--format", "csv", "--block", "{d}/lot/SIM-000001.csv",
                    "--mode", "compensated", "--seconds", "0.2", "--speed-rpm", "60", "--iq", "10", "--seed", "1"])


BAD_SETTINGS: tuple[tuple[str, dict[str, str]], ...] = (
    ("estimator foo", {"estimator": '"foo"'}), ("db .", {"db": '"."'}), ("db sqlite://", {"db": '"sqlite:///x.sqlite"'}),
    ("db psycopg2", {"db": '"postgresql+psycopg2://u@h/eol"'}), ("db mysql", {"db": '"mysql://u@h/eol"'}),
    ("db malformed URL", {"db": '"postgresql://u@h:port/eol"'}), ("db no directory", {"db": '"no/such/r.sqlite"'}),
    ("db a device", {"db": '"/dev/null"'}), ("key_algo missing", {"key_algo": '"no-such-oem"'}),
    ("key_algo fails", {"key_algo": '"json:loads"'}),
)
BAD_DYNO = ("a b", "http://192.0.2.10", "http://dyno:502", "dyno_3", "[zz]:502")


def refusal_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """Values that must be refused before anything runs."""
    for name, keys in BAD_SETTINGS:
        yield Scenario("refusals", f"settings {name}", station_files(**keys), RUN)
    for dyno in BAD_DYNO:
        files = station_files()
        files["station.toml"] = files["station.toml"].replace(b'"127.0.0.1:1"', f'"{dyno}"'.encode())
        yield Scenario("refusals", f"settings dyno.address {dyno}", files, RUN)
    for name, cfg in (("garbage", b"\x00\x01garbage [[[\n= = =\n"), ("bit rate", b"[default]\nbitrate = fast\n")):
        files = {**station_files(), "can.ini": cfg}
        files["station.toml"] = files["station.toml"].replace(b'channel = "nobody"\n',
                                                              b'channel = "nobody"\nconfig = "can.ini"\n')
        yield Scenario("refusals", f"settings can.config {name}", files, RUN)

    limits = file_bytes(FIXTURES / "limits.toml")
    key = next(lim.key for lim in LIMITS if lim.quantity == "mech1_after_nm")  # revision 1.2's row
    for value in ("-0.001", "11.0", "nan", "inf", '"0.01"', "true", "[0.01]", "1" + "0" * 30):
        row = f"{key} = {value}\n".encode()
        files = {**station_files(), "limits.toml": limits.replace(b"[variant.EPS-STD]\n", b"[variant.EPS-STD]\n" + row)}
        yield Scenario("refusals", f"limits {key} = {value}", files, RUN)
    fit = json.loads((FIXTURES / "fit_paper.json").read_text())
    for serial in ("", "   ", " M-1", "M\x001", "M\t1", "X" * 17, "Mé"):
        doc = json.loads(json.dumps(fit))
        doc["motors"][0]["serial"] = serial
        yield Scenario("refusals", f"fit result serial {serial!r}", {"fit.json": json.dumps(doc).encode()},
                       ["table", "{d}/fit.json", "-o", "{d}/b.bin"])
    yield from _mech_scenarios()
    yield from _ecu_state_scenarios()


#: a fit result's ``mech`` object with a value that must be refused: (name, key path, value)
BAD_MECH: tuple[tuple[str, tuple, object], ...] = (
    ("status", ("status",), "maybe"), ("dirs", ("dirs",), 4), ("grid_phase", ("grid_phase",), 7.0),
    ("fingerprint short", ("fingerprint",), [0.0] * 3), ("fingerprint 2 rad", ("fingerprint", 0), 2.0),
    ("sigma negative", ("sigma", 0), -1.0), ("window", ("windows", 0), 64), ("margin NaN", ("margin", "predicted"), "NaN"),
    ("threshold", ("margin", "threshold"), 9.0), ("order 1 c", ("orders", 0, "c", "value"), 1e6),
    ("order 1 phase", ("orders", 0, "phase_c", "value"), 1e3), ("order as text", ("orders", 0, "order"), "1"),
    ("order 9", ("orders", 0, "order"), 9), ("order 1 twice", ("orders", 1, "order"), 1),
    ("order 0", ("orders", 0, "order"), 0),
)


def _mech_scenarios() -> Iterator[Scenario]:
    """Fit results of revision 1.2 whose ``mech`` object must be refused by ``table`` (layout 2)."""

    base = fit_result_with_mech(file_bytes(FIXTURES / "fit_paper.json"))
    for name, path, value in BAD_MECH:
        doc = json.loads(base)
        at = doc["motors"][0]["mech"]
        for k in path[:-1]:
            at = at[k]
        at[path[-1]] = "@@"
        data = json.dumps(doc).replace('"@@"', value if value == "NaN" else json.dumps(value)).encode()
        yield Scenario("refusals", f"fit result mech.{name}", {"fit.json": data}, ["table", "{d}/fit.json", "-o", "{d}/b.bin"])


def _ecu_state_scenarios() -> Iterator[Scenario]:


    for keep in ("ecu_before", "ecu_after"):
        for suffix in (".csv", ".mf4"):
            yield Scenario("refusals", f"ECU state only {keep} ({suffix})",
                           {f"c{suffix}": functools.partial(_one_ecu_state, keep, suffix)},
                           ["capture", "info", f"{{d}}/c{suffix}"])


def _one_ecu_state(keep: str, suffix: str) -> bytes:
    """A capture whose metadata hold the ECU's state ``keep`` (``ecu_before`` or ``ecu_after``) alone."""
    drop = "ecu_after" if keep == "ecu_before" else "ecu_before"
    cap = synthetic_capture(rpm=60.0, seconds=0.5, fs=5000.0, serial="F-0001", seed=7)
    cap.metadata.pop(f"{drop}.bank", None)
    cap.metadata.update({f"{keep}.bank": "1", f"{keep}.sequence": 2, f"{keep}.crc32": "5be1c0a7",
                         f"{keep}.flags": "INTERP_ENABLE"})
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"c{suffix}"
        write_capture(cap, path)
        return path.read_bytes()


def exit_scenarios(bases: Mapping[str, bytes]) -> Iterator[Scenario]:
    """Bad input to refit: exit 2 before any cluster starts."""
    files = {"lot/c.csv": bases["csv"], "limits.toml": file_bytes(FIXTURES / "limits.toml"), "bad.toml": b"x = \n"}
    base = ["refit", "{d}/lot", "-o", "{d}/rows.jsonl"]
    for name, extra in (("bad limits", ["--limits", "{d}/bad.toml"]), ("unknown variant", ["--limits", "{d}/limits.toml",
                        "--variant", "NOPE"]), ("variant without limits", ["--variant", "EPS-STD"]),
                        ("unknown motor", ["--motor", "nope"]), ("unknown bench", ["--bench", "nope"]),
                        ("scheduler garbage", ["--scheduler", "garbage"]), ("scheduler URL", ["--scheduler", "http://x:1"])):
        yield Scenario("exits", f"refit {name}", files, [*base, *extra])


#: kind -> builder(bases) of its scenarios
BUILDERS: dict[str, Callable[[Mapping[str, bytes]], Iterator[Scenario]]] = {
    "toml": lambda bases: toml_scenarios(), "json": lambda bases: json_scenarios(), "captures": capture_scenarios,
    "paths": path_scenarios, "refusals": refusal_scenarios, "exits": exit_scenarios,
}


# ------------------------------------------------------------------------------------ running


@dataclass
class ScenarioOutcome:
    """How the CLI ended on one scenario."""

    scenario: Scenario
    rc: int | None
    seconds: float
    stderr: str
    traceback: bool
    hang: bool
    crash: bool
    modified: bool
    should_refuse: bool

    @property
    def clean(self) -> bool:
        return not (self.traceback or self.hang or self.crash or self.modified or self.should_refuse)

    @property
    def what(self) -> str:
        for flag in ("hang", "crash", "traceback", "modified", "should_refuse"):
            if getattr(self, flag):
                return "accepted-should-refuse" if flag == "should_refuse" else flag
        return "ok"


def run_scenario(scenario: Scenario, workdir: Path, timeout_s: float = 60.0, root: Path = ROOT) -> ScenarioOutcome:
    """Lay ``scenario`` out in a new directory under ``workdir``, run it, judge it."""

    d = workdir / uuid.uuid4().hex[:12]
    scenario.lay_out(d)
    before = scenario.digests(d)
    rc, out, err, seconds, _rss = run_cli(scenario.argv(d), d, timeout_s, scenario.memory_bytes or CHILD_MEMORY_BYTES, root,
                                         stdin=scenario.stdin, env=scenario.env, signal_at=scenario.signal_at)
    after = scenario.digests(d)
    shutil.rmtree(d, ignore_errors=True)
    text = out + err
    crash = rc is not None and (rc not in (0, 1, 2) or "MemoryError" in text)
    last = (err.strip().splitlines() or [""])[-1]
    # a signal that came while the command ran must end it with exit 2 (its own line says what was
    # interrupted); one after its end changes nothing
    signalled = scenario.signal_at is not None and seconds > scenario.signal_at[1]
    refused = rc == 2 and (signalled or last.startswith(("error:", "Error:")))  # ours, or click's usage error
    must_refuse = scenario.expect == "refuse" or signalled
    return ScenarioOutcome(scenario, rc, seconds, err[-2000:], "Traceback" in text, rc is None, crash, after != before,
                           must_refuse and rc is not None and not refused and not crash)


@dataclass
class ScenarioTally(Counts):
    """Counts of one kind of scenario."""

    refused: int = 0
    accepted: int = 0
    should_refuse: int = 0

    def add(self, o: ScenarioOutcome) -> None:
        self.tried += 1
        self.refused += o.rc == 2 and not o.crash
        self.accepted += o.rc in (0, 1) and not o.crash
        self.should_refuse += o.should_refuse
        self.tracebacks += o.traceback
        self.hangs += o.hang
        self.crashes += o.crash
        self.modified += o.modified
        self.max_seconds = max(self.max_seconds, o.seconds)
        if not o.clean:
            self.bad.append(o)


def all_builders() -> dict[str, Callable[[Mapping[str, bytes]], Iterator[Scenario]]]:
    """The builders of this module and of every other scenario module present
    (``eol_cal.sim.fuzz.scenarios_*``: each adds its own ``BUILDERS``; none is needed)."""

    out = dict(BUILDERS)
    for info in sorted(pkgutil.iter_modules(fuzz_package.__path__), key=lambda m: m.name):
        if info.name.startswith("scenarios_"):
            out.update(getattr(importlib.import_module(f"eol_cal.sim.fuzz.{info.name}"), "BUILDERS", {}))
    return out


def run_scenarios(kinds: tuple[str, ...], workdir: Path, bases: Mapping[str, bytes], timeout_s: float = 60.0,
                  root: Path = ROOT, progress: Callable[[str], None] | None = None) -> dict[str, ScenarioTally]:
    """Every scenario of ``kinds`` (of :func:`all_builders`); a :class:`ScenarioTally` per kind."""
    builders = all_builders()
    tallies: dict[str, ScenarioTally] = {}
    for kind in kinds:
        tally = tallies.setdefault(kind, ScenarioTally())
        for scenario in builders[kind](bases):
            tally.add(run_scenario(scenario, workdir, timeout_s, root))
            if progress is not None:
                progress(f"{kind}: {scenario.name}")
    return tallies
