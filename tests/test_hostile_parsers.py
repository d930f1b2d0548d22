"""Parsers with bounds (issue 23, class 4): every TOML file the tool reads (settings, limits,
channel and register maps, motors, benches, profiles) and every JSON input (fit results, spool
files, refit results, stored records) goes through one bounded loader (``eol_cal.infra.inputs``).
A number of thousands of digits, nesting thousands deep, an oversized file or a FIFO ends in one
line naming the file and exit 2, never a traceback or a hang; the CSV header and the MDF4
record count are parsed within bounds too."""

from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from test_hostile_files import _one_line_exit_2
from eol_cal.ecu import protocol as P
from eol_cal.errors import InputError
from eol_cal.sim.fuzz import hostile
from eol_cal.infra.inputs import MAX_NESTING, MAX_TOML_BYTES, loads_json, loads_toml

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"

#: hostile TOML text, each placed at the top of an otherwise valid file
TOML_HOSTILE = {
    "5000-digit integer": "zz = " + "9" * 5000 + "\n",
    "400-digit integer": "zz = " + "9" * 400 + "\n",
    "integer beyond 64 bits": "zz = 9223372036854775808\n",
    "arrays 5000 deep": "zz = " + "[" * 5000 + "]" * 5000 + "\n",
    "arrays 100 deep": "zz = " + "[" * 100 + "]" * 100 + "\n",
    "inline tables 5000 deep": "zz = " + "{a=" * 5000 + "1" + "}" * 5000 + "\n",
    "dotted key 5000 deep": "zz" + ".a" * 5000 + " = 1\n",
    "table header 300 deep": "[" + ".".join(["t"] * 300) + "]\nx = 1\n",
}


def _env() -> dict[str, str | None]:
    return {k: None for k in os.environ if k.startswith("EOL_CAL_") and k != "EOL_CAL_JAX_CACHE"}


def _station(d: Path, **keys: str) -> Path:
    """A valid station settings file in ``d`` (its dyno and bus go nowhere: every check here
    refuses before they are used); ``keys`` replace its top-level keys."""
    (d / "ecu.key").write_text(P.DEV_SECRET.hex() + "\n")
    (d / "limits.toml").write_bytes((FIXTURES / "limits.toml").read_bytes())
    values = {"station_id": '"L3"', "limits": '"limits.toml"', "db": '"records.sqlite"', "key_file": '"ecu.key"',
              **keys}
    path = d / "station.toml"
    path.write_text("".join(f"{k} = {v}\n" for k, v in values.items())
                    + '[dyno]\naddress = "127.0.0.1:1"\n[can]\ninterface = "remote"\nchannel = "ws://127.0.0.1:1/"\n')
    return path


def _valid_toml(kind: str) -> str:
    return {
        "limits": (FIXTURES / "limits.toml").read_text(),
        "motor": "poles = 6\n",
        "bench": (ROOT / "eol_cal" / "benches" / "paper.toml").read_text(),
        "profile": (ROOT / "eol_cal" / "profiles" / "paper.toml").read_text(),
        "register_map": (ROOT / "eol_cal" / "dyno" / "maps" / "default.toml").read_text(),
        "map": (FIXTURES / "daq_export_foreign.map.toml").read_text(),
        "settings": "",
    }[kind]


def _invoke_with(kind: str, tmp_path: Path, hostile: Path):
    """Run the command that reads a TOML file of ``kind``, given as ``hostile``."""
    if kind == "map":
        return CliRunner().invoke(cli, ["capture", "info", "--map", str(hostile),
                                        str(FIXTURES / "daq_export_foreign.csv")])
    if kind == "settings":
        station = hostile
    else:
        key = {"register_map": None}.get(kind, kind)
        station = _station(tmp_path, **({key: json.dumps(str(hostile))} if key else {}))
        if kind == "register_map":
            station.write_text(station.read_text().replace("[dyno]\n", f"[dyno]\nregister_map = {json.dumps(str(hostile))}\n"))
    return CliRunner().invoke(cli, ["run", "--station", str(station), "--serial", "M-1"], env=_env())


TOML_KINDS = ("settings", "limits", "motor", "bench", "profile", "register_map", "map")


@pytest.mark.parametrize("kind", TOML_KINDS)
@pytest.mark.parametrize("case", sorted(TOML_HOSTILE))
def test_hostile_toml_of_every_kind_is_one_line_naming_the_file(tmp_path, kind, case):
    hostile = tmp_path / f"hostile-{kind}.toml"
    valid = _valid_toml(kind) if kind != "settings" else _station(tmp_path).read_text()
    hostile.write_text(TOML_HOSTILE[case] + valid)
    res = _invoke_with(kind, tmp_path, hostile)
    _one_line_exit_2(res, str(hostile))


@pytest.mark.parametrize("kind", TOML_KINDS)
def test_oversized_toml_and_a_fifo_are_refused_unread(tmp_path, kind):
    big = tmp_path / f"big-{kind}.toml"
    big.write_text(("#" * 1023 + "\n") * (MAX_TOML_BYTES // 1024 + 1))
    _one_line_exit_2(_invoke_with(kind, tmp_path, big), str(big), "bytes")
    fifo = tmp_path / f"fifo-{kind}.toml"
    os.mkfifo(fifo)
    _one_line_exit_2(_invoke_with(kind, tmp_path, fifo), str(fifo), "FIFO")


def test_the_loader_keeps_valid_documents_and_names_the_path_of_a_bad_value():
    assert loads_toml("a = 9223372036854775807\n[b.c]\nd = [[1], [2]]\n", "x.toml") == {
        "a": 2**63 - 1, "b": {"c": {"d": [[1], [2]]}}}
    nested = "a = " + "[" * (MAX_NESTING - 1) + "]" * (MAX_NESTING - 1)
    loads_toml(nested, "x.toml")  # at the bound: kept
    with pytest.raises(InputError, match="nested deeper"):
        loads_toml("a = " + "[" * (MAX_NESTING + 1) + "]" * (MAX_NESTING + 1), "x.toml")
    with pytest.raises(InputError) as err:
        loads_json('{"motors": [{"k6": {"value": NaN}}]}', "f.json")
    assert err.value.field == "motors[0].k6.value" and err.value.file == "f.json"
    for text in ("1e400", "-Infinity", "[" + "9" * 400 + "]", "9" * 5000, "[" * 70 + "]" * 70):
        with pytest.raises(InputError):
            loads_json(text, "f.json")
    assert loads_json('{"a": [1.5, -9223372036854775808, null]}', "f.json") == {"a": [1.5, -2**63, None]}


def test_a_dotted_key_of_a_megabyte_is_refused_before_the_parser_spends_hours_on_it():
    """Python's TOML parser is quadratic in a dotted key's parts (10 000 parts: 4 s; this file, one
    key of 500 000 parts within the 1 MiB a TOML input may have: hours). Refused before parsing; a
    key at the bound, quoted parts, spaces around the dots and 100 000 floats are as before."""
    with pytest.raises(InputError, match="dotted key of more than 64 parts"):
        loads_toml("zz" + ".a" * 500_000 + " = 1\n", "x.toml")
    with pytest.raises(InputError, match="dotted key"):
        loads_toml("zz" + ' . "a b"' * (MAX_NESTING + 1) + " = 1\n", "x.toml")
    deepest = "zz" + ".a" * (MAX_NESTING - 2) + " = 1\n"
    assert _leaf(loads_toml(deepest, "x.toml")) == 1
    assert len(loads_toml("x = [" + ", ".join(["1.5"] * 100_000) + "]\n", "x.toml")["x"]) == 100_000
    assert loads_toml('v = "1.2.3"\n[a."b.c".d]\ne = 2.5\n', "x.toml") == {"v": "1.2.3", "a": {"b.c": {"d": {"e": 2.5}}}}


def _leaf(doc: dict) -> object:
    while isinstance(doc, dict):
        (doc,) = doc.values()
    return doc


@pytest.mark.parametrize("line", [
    '{"serial": "M-1", "verdict": NaN}', "[" * 5000 + "]" * 5000, '{"serial": ' + "9" * 5000 + "}", "[]", '"text"',
    '{"serial": "M-1", "verdict": "pass", "k6": 1e999}',
])
def test_lot_diff_refuses_a_hostile_refit_row_naming_the_file(tmp_path, line):
    from eol_cal.records.record import RunRecord
    from eol_cal.records.write import insert_records

    db = tmp_path / "r.sqlite"
    insert_records(db, [RunRecord.from_json(json.loads((FIXTURES / "run_record_demo.json").read_text()))])
    rows = tmp_path / "refit.jsonl"
    rows.write_text('{"serial": "M-0", "verdict": "pass"}\n' + line + "\n")
    res = CliRunner().invoke(cli, ["lot", "diff", "--db", str(db), str(rows)])
    _one_line_exit_2(res, str(rows))


def test_a_stored_record_holding_nan_is_skipped_and_named(tmp_path):
    """A record row written by another tool with NaN in it: ``records --json`` names the run and
    goes on with the others (it used to end in ``ValueError: Out of range float values``)."""
    from eol_cal.records.record import RunRecord
    from eol_cal.records.write import insert_records

    db = tmp_path / "r.sqlite"
    rec = json.loads((FIXTURES / "run_record_demo.json").read_text())
    insert_records(db, [RunRecord.from_json(rec)])
    with sqlite3.connect(db) as con:
        text = con.execute("SELECT record_json FROM runs").fetchone()[0]
        doc = json.loads(text)
        doc["run_id"] = "bad-run"
        doc["metrics"] = {"pp_before_pct": "@@"}
        con.execute("UPDATE runs SET record_json = ?", (json.dumps(doc).replace('"@@"', "NaN"),))
    res = CliRunner().invoke(cli, ["records", "--db", str(db), "--json"])
    assert "Traceback" not in res.output and res.exit_code in (0, 2), res.output
    assert "not a finite number" in res.output or "NaN" in res.output, res.output


def test_spool_files_are_read_with_the_bounded_loader(tmp_path):
    from eol_cal.records.spool import flush_spool

    spool = tmp_path / "spool"
    spool.mkdir()
    (spool / "deep.json").write_text("[" * 100000 + "]" * 100000)
    (spool / "digits.json").write_text('{"schema": ' + "9" * 5000 + "}")
    (spool / "nan.json").write_text('{"schema": NaN}')
    os.mkfifo(spool / "fifo.json")
    res = flush_spool(tmp_path / "r.sqlite", spool)  # a FIFO read would block (pytest-timeout ends it)
    assert len(res.bad_files) == 4, res.bad_files
    assert all(str(spool) in b for b in res.bad_files)


@pytest.mark.parametrize("args", [
    ["records", "--db", "{db}"], ["records", "--db", "{db}", "--flush", "--spool-dir", "{tmp}/spool"],
    ["lot", "report", "--db", "{db}", "-o", "{tmp}/lot.html"], ["lot", "stats", "--db", "{db}"],
    ["lot", "diff", "--db", "{db}", "{rows}"],
])
def test_a_fifo_or_a_device_as_the_records_database_is_refused_not_opened(tmp_path, args):
    """SQLite opens a FIFO and blocks in the kernel (retrying through SIGTERM): every command
    that reads the database refuses it first (pytest-timeout ends the test if one blocks)."""
    rows = tmp_path / "refit.jsonl"
    rows.write_text('{"serial": "M-0", "verdict": "pass"}\n')
    fifo = tmp_path / "records.sqlite"
    os.mkfifo(fifo)
    for db in (fifo, Path("/dev/zero")):
        argv = [a.format(db=db, tmp=tmp_path, rows=rows) for a in args]
        res = CliRunner().invoke(cli, argv)
        assert res.exit_code == 2 and "Traceback" not in res.output, res.output
        assert str(db) in res.stderr.strip().splitlines()[-1], res.output
    assert not (tmp_path / "lot.html").exists()


@pytest.fixture(scope="module")
def bases(tmp_path_factory) -> dict[str, bytes]:
    from eol_cal.sim.fuzz import base_files

    return base_files()


@pytest.mark.parametrize("case", sorted(hostile.CSV_HEADER_CELLS) + sorted(hostile.CSV_META_LINES))
def test_hostile_csv_header_and_metadata_lines_are_parsed_in_linear_time(bases, tmp_path, case):
    """A header cell of 200 000 ``[`` made a backtracking regular expression run for minutes;
    each of these now ends at once (pytest-timeout would end a quadratic one)."""
    path = tmp_path / "hostile.csv"
    if case in hostile.CSV_HEADER_CELLS:
        path.write_bytes(hostile.csv_with_header_cell(bases["csv"], hostile.CSV_HEADER_CELLS[case]))
    else:
        path.write_bytes(hostile.csv_with_meta_line(bases["csv"], hostile.CSV_META_LINES[case]))
    res = CliRunner().invoke(cli, ["capture", "info", str(path)])
    assert res.exit_code in (0, 2) and "Traceback" not in res.output, res.output
    if res.exit_code:
        assert str(path) in res.stderr.strip().splitlines()[-1]
        assert len(res.stderr.strip().splitlines()[-1]) < 2000  # a 200 000-character unit is not echoed whole


@pytest.mark.parametrize("field, value", [(f, v) for f, vs in hostile.MDF4_CG_FIELDS.items() for v in vs])
def test_mdf4_record_counts_and_flags_a_decoder_would_believe_are_refused(bases, tmp_path, field, value):
    """0 claimed records made asammdf split the data into empty records without end (2.6 GB and
    rising); a variable-length-data flag made it malloc a size from the record fields (abort).
    Run in a child under the fault benchmark's 2 GiB address-space limit."""
    from eol_cal.sim.fuzz import run_cli

    path = tmp_path / "hostile.mf4"
    path.write_bytes(hostile.mdf4_with_cg_field(bases["mdf4"], field, value))
    rc, _out, err, _s, _rss = run_cli(["capture", "info", str(path)], tmp_path, timeout_s=120)
    assert rc == 2 and "Traceback" not in err and "MemoryError" not in err, err
    assert str(path) in err.strip().splitlines()[-1] and "block ##" in err, err


def test_mdf4_zero_records_is_refused_by_the_structure_check_naming_the_group(bases):
    from eol_cal.capture.mdf4_check import check_mdf4_bytes

    with pytest.raises(InputError, match="claims 0 records") as err:
        check_mdf4_bytes(hostile.mdf4_with_cg_field(bases["mdf4"], "cycles", 0), "x.mf4")
    assert err.value.field.startswith("block ##CG")


def test_a_fifo_as_key_file_or_golden_vector_file_is_refused_unread(tmp_path):
    from eol_cal.firmware.example import example_block

    block = tmp_path / "b.bin"
    block.write_bytes(example_block(serial="M-0007"))
    fifo = tmp_path / "ecu.key"
    os.mkfifo(fifo)
    res = CliRunner().invoke(cli, ["flash", str(block), "-i", "virtual", "-c", "nobody-listens", "--key-file", str(fifo)])
    _one_line_exit_2(res, str(fifo), "FIFO")
    golden = tmp_path / "golden"
    golden.mkdir()
    os.mkfifo(golden / "manifest.json")
    res = CliRunner().invoke(cli, ["golden", "--check", str(golden)])  # refused before the vectors are computed
    assert res.exit_code == 2 and "Traceback" not in res.output and "FIFO" in res.output, res.output
