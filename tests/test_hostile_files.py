"""Hostile file arguments (issue 16, items 5 and 6): an output that is an input, a device or a
FIFO; non-UTF-8 TOML, a wrong key algorithm, a corrupt record row, a full disk, deeply nested or
huge-number JSON, the fit-JSON values of the issue. Each ends in one line naming the file, exit 2,
and nothing modified or half-written."""

from __future__ import annotations

import hashlib
import json
import os
import resource
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from _capture_helpers import small_capture
from cli.main import cli
from eol_cal.capture.io import write_capture
from eol_cal.sim.virtual_rig import example_block

ROOT = Path(__file__).resolve().parents[1]
FIT = ROOT / "fixtures" / "fit_paper.json"


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _one_line_exit_2(res, *words: str) -> str:
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output, res.output
    line = res.stderr.strip()
    assert len(line.splitlines()) == 1, line
    for w in words:
        assert w in line, line
    return line


@pytest.fixture()
def files(tmp_path: Path) -> dict[str, Path]:
    csv, block, fit = tmp_path / "c.csv", tmp_path / "b.bin", tmp_path / "f.json"
    write_capture(small_capture(), csv)
    block.write_bytes(example_block(serial="M-0007"))
    fit.write_bytes(FIT.read_bytes())
    return {"csv": csv, "block": block, "fit": fit}


@pytest.mark.parametrize("args", [
    ["fit", "{csv}", "-o", "{csv}"],
    ["analyze", "{csv}", "--plot", "{csv}"],
    ["table", "{fit}", "-o", "{fit}"],
    ["table", "{fit}", "-o", "{dir}/new.bin", "--hex", "{fit}"],
    ["block", "hex", "{block}", "--bank", "0", "-o", "{block}"],
    ["capture", "convert", "{csv}", "{csv}"],
])
def test_output_that_is_an_input_is_refused_and_the_input_kept(files, tmp_path, args):
    argv = [a.format(dir=tmp_path, **files) for a in args]
    before = {k: _digest(p) for k, p in files.items()}
    res = CliRunner().invoke(cli, argv)
    _one_line_exit_2(res, "output is also an input")
    assert {k: _digest(p) for k, p in files.items()} == before


def test_the_same_file_by_another_name_is_the_same_file(files, tmp_path):
    link, hard = tmp_path / "link.csv", tmp_path / "hard.csv"
    link.symlink_to(files["csv"])
    os.link(files["csv"], hard)
    before = _digest(files["csv"])
    for other in (link, hard, Path(os.path.relpath(files["csv"]))):
        res = CliRunner().invoke(cli, ["analyze", str(files["csv"]), "--plot", str(other)])
        _one_line_exit_2(res, str(other), "output is also an input")
    res = CliRunner().invoke(cli, ["table", str(files["fit"]), "-o", str(tmp_path / "x.bin"), "--hex", str(tmp_path / "x.bin")])
    _one_line_exit_2(res, "two outputs")
    assert _digest(files["csv"]) == before and not (tmp_path / "x.bin").exists()


def test_device_and_fifo_outputs_are_refused_without_blocking(files, tmp_path):
    fifo = tmp_path / "out.bin"
    os.mkfifo(fifo)
    res = CliRunner().invoke(cli, ["block", "hex", str(files["block"]), "--bank", "0", "-o", str(fifo)])
    _one_line_exit_2(res, str(fifo), "FIFO")
    res = CliRunner().invoke(cli, ["capture", "convert", str(files["csv"]), "/dev/null"])
    _one_line_exit_2(res, "/dev/null", "character device")
    assert Path("/dev/null").is_char_device()


def test_non_utf8_motor_and_bench_toml_name_the_file(files, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b'poles = 6\nname = "\xff\xfe"\n')
    res = CliRunner().invoke(cli, ["table", str(files["fit"]), "-o", str(tmp_path / "o.bin"), "--motor", str(bad)])
    _one_line_exit_2(res, str(bad), "not UTF-8")
    res = CliRunner().invoke(cli, ["block", "uncompensated", "--serial", "X", "-o", str(tmp_path / "u.bin"),
                                   "--motor", str(bad)])
    _one_line_exit_2(res, str(bad), "not UTF-8")
    from eol_cal.domain.bench_mechanics import load_mechanics
    from eol_cal.errors import InputError

    with pytest.raises(InputError, match="not UTF-8") as info:  # what `fit --bench FILE` reads it with
        load_mechanics(bad)
    assert info.value.file == str(bad)


@pytest.mark.parametrize("algo, words", [
    ("json:loads", ["json", "failed on the seed"]),
    ("os:nothing_here", ["os.py", "no function"]),
    ("no_such_module_xyz:f", ["cannot load", "no_such_module_xyz"]),
    ("justaname", ["no entry point", "MODULE:FUNC"]),
])
def test_wrong_key_algo_is_refused_before_the_bus_opens(files, algo, words):
    res = CliRunner().invoke(cli, ["flash", str(files["block"]), "-i", "virtual", "-c", "nobody-listens",
                                   "--key-algo", algo])
    _one_line_exit_2(res, "key-algo", *words)


def test_a_corrupt_record_row_is_skipped_and_reported_the_others_kept(tmp_path):
    from test_station_records import record

    from eol_cal.records.write import insert_records

    db = tmp_path / "r.sqlite"
    recs = [record(serial, started=f"2026-11-22T0{k}:00:00.000+00:00") for k, serial in enumerate("ABC")]
    insert_records(db, recs)
    con = sqlite3.connect(db)
    con.execute("UPDATE runs SET record_json = ? WHERE serial = 'B'", ('{"schema": "eol-cal/run-record/1", "serial": ',))
    con.commit()
    con.close()
    res = CliRunner().invoke(cli, ["records", "--db", str(db), "--json"])
    line = _one_line_exit_2(res, str(db), "record_json", "skipped")
    assert recs[1].run_id not in line or "run" in line
    assert [r["serial"] for r in json.loads(res.stdout)["records"]] == ["A", "C"]
    # lot statistics read the columns, not the record JSON: the corrupt document does not matter
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(db), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["runs"] == 3
    # a corrupt reasons column of a failed run is refused, naming the database, the run and the column
    con = sqlite3.connect(db)
    con.execute("UPDATE runs SET verdict = 'fail', causes = '[\"max_' WHERE serial = 'C'")
    con.commit()
    con.close()
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(db)])
    _one_line_exit_2(res, str(db), recs[2].run_id, "causes")


def _full_disk(tmp_path: Path) -> Path | None:
    """A 64 KiB tmpfs (a real ENOSPC), or None where this machine may not mount one."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)], capture_output=True).returncode == 0
    return mnt if ok else None


def test_a_full_disk_on_the_output_leaves_nothing_and_exits_2(files, tmp_path):
    """ENOSPC on a real tmpfs; where mounting is not allowed, EFBIG from RLIMIT_FSIZE: the same
    failing write path (the OS refuses the bytes), so the same promise is checked."""
    mnt = _full_disk(tmp_path)
    try:
        if mnt is not None:
            (mnt / "filler").write_bytes(b"\0" * 60 * 1024)
            res = CliRunner().invoke(cli, ["capture", "convert", str(files["csv"]), str(mnt / "out.csv")])
            _one_line_exit_2(res, str(mnt / "out.csv"), "No space left on device")
            assert sorted(p.name for p in mnt.iterdir()) == ["filler"]  # no temporary file left
            return
        out = tmp_path / "out.csv"

        def small_files() -> None:
            import signal

            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

        proc = subprocess.run([sys.executable, "-m", "cli.main", "capture", "convert", str(files["csv"]), str(out)],
                              capture_output=True, text=True, preexec_fn=small_files,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert proc.returncode == 2 and str(out) in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert not out.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".out")] == []
    finally:
        if mnt is not None:
            subprocess.run(["umount", str(mnt)], check=False)


@pytest.mark.parametrize("patch, words", [
    (lambda m: m.__setitem__("c6", 1e30), ["motors[0].c6"]),
    (lambda m: m.__setitem__("k6", True), ["motors[0].k6", "boolean"]),
    (lambda m: m.__setitem__("k6", "0.0006"), ["motors[0].k6", "string"]),
    (lambda m: m.__setitem__("k6", -5), ["motors[0].k6"]),
])
def test_the_issues_fit_json_values_are_refused_naming_file_and_field(tmp_path, patch, words):
    doc = json.loads(FIT.read_text())
    patch(doc["motors"][0])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    res = CliRunner().invoke(cli, ["table", str(bad), "-o", str(tmp_path / "o.bin")])
    _one_line_exit_2(res, str(bad), *words)
    assert not (tmp_path / "o.bin").exists()


@pytest.mark.parametrize("token, words", [
    ("[" * 100000 + "]" * 100000, ["nested deeper"]),
    ("[" * 1000 + "]" * 1000, ["nested deeper"]),
    ("9" * 5000, ["not valid JSON", "digits"]),
    ("1e400", ["motors[0].k6"]),
])
def test_deeply_nested_or_huge_number_json_is_one_line(tmp_path, token, words):
    text = FIT.read_text()
    doc = json.loads(text)
    doc["motors"][0]["k6"]["value"] = "@@"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc).replace('"@@"', token))
    res = CliRunner().invoke(cli, ["table", str(bad), "-o", str(tmp_path / "o.bin")])
    _one_line_exit_2(res, str(bad), *words)
