"""Every database file is an input (issue 36, class 1) and no page or command crashes on an odd
selection (class 5).

Class 1: no output of any command lands on a records database or a file SQLite keeps beside it
(``-wal``, ``-shm``, ``-journal``), whether it exists yet or not, by any route: an option, a
setting, a default, a file the command creates itself (``station --demo --lot D/results.sqlite``
replaced the database it had just made with the lot page, exit 0). Class 5: the lot page, the
records, the statistics of a selection with no run, one, only refusals, only the master's runs,
only simulated or restore runs.

Real parts: SQLite, the CLI through click.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.infra.atomic import atomic_write
from eol_cal.errors import InputError
from eol_cal.infra.inputs import command_inputs, protect_database
from eol_cal.records.migrations import migrate
from eol_cal.records.write import insert_records

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def _db(path: Path, records=()) -> Path:
    migrate(path)
    if records:
        insert_records(path, list(records))
    return path


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else "-"


def _refused(res, names: str) -> str:
    assert res.exit_code == 2, res.output
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("error:") and names in line, res.output
    return line


# ------------------------------------------------------------------------------------------ class 1


@pytest.mark.parametrize("args, victim", [
    (["records", "--db", "{d}/r.sqlite", "--plot", "{d}/r.sqlite-wal"], "r.sqlite-wal"),
    (["lot", "report", "--db", "{d}/r.sqlite", "-o", "{d}/r.sqlite-shm"], "r.sqlite-shm"),
    (["lot", "stats", "--db", "{d}/r.sqlite", "--csv", "{d}/r.sqlite-journal"], "r.sqlite-journal"),
    (["lot", "report", "--db", "{d}/r.sqlite", "-o", "{d}/./r.sqlite"], "r.sqlite"),
    (["analyze", str(FIXTURES / "paper_60rpm.csv"), "--plot", "{d}/other.sqlite"], "other.sqlite"),
    (["table", str(FIXTURES / "fit_paper.json"), "-o", "{d}/other.sqlite"], "other.sqlite"),
    (["capture", "convert", str(FIXTURES / "paper_60rpm.csv"), "{d}/other.sqlite-wal"], "other.sqlite-wal"),
])
def test_no_output_lands_on_a_database_file(tmp_path, args, victim):
    db = _db(tmp_path / "r.sqlite", [make_record("M-1")])
    other = _db(tmp_path / "other.sqlite", [make_record("M-2")])
    (tmp_path / "other.sqlite-wal").write_bytes(b"\x37\x7f\x06\x82" + b"\0" * 28)  # a write-ahead log's header
    digests = {p: _digest(p) for p in tmp_path.iterdir()}
    res = CliRunner().invoke(cli, [a.format(d=tmp_path) for a in args])
    _refused(res, victim)
    assert {p: _digest(p) for p in tmp_path.iterdir()} == digests  # nothing written, nothing created
    assert db.exists() and other.exists()


@pytest.mark.parametrize("args", [
    ["--lot", "{d}/D/results.sqlite"],             # the lot page over the database the demo makes
    ["--db", "{d}/D/lot.html"],                     # the default lot page over the given database
    ["--db", "{d}/D/limits.toml"],                  # the demo's limits over the given database
    ["--lot", "{d}/D/results.sqlite-wal"],
])
def test_station_demo_checks_its_own_files_against_its_database_first(tmp_path, args):
    (tmp_path / "D").mkdir()
    db = _db(tmp_path / "D" / "results.sqlite", [make_record("M-1")])
    before = _digest(db)
    res = CliRunner().invoke(cli, ["station", "--demo", "--out", str(tmp_path / "D"), *[a.format(d=tmp_path) for a in args]],
                             input="bob\nq\n")
    _refused(res, "database")
    assert _digest(db) == before and not (tmp_path / "D" / "lot.html").exists()


def test_demo_checks_its_limits_and_lot_page_against_its_database(tmp_path):
    (tmp_path / "D").mkdir()
    db = _db(tmp_path / "D" / "limits.toml", [make_record("M-1")])
    before = _digest(db)
    res = CliRunner().invoke(cli, ["demo", "--motors", "1", "--out", str(tmp_path / "D"), "--db", str(db)])
    _refused(res, "limits.toml")
    assert _digest(db) == before


def test_a_database_named_before_it_exists_takes_no_output(tmp_path):
    db = tmp_path / "new.sqlite"
    with command_inputs():
        protect_database(db)
        for victim in (db, Path(f"{db}-wal"), Path(f"{db}-journal")):
            with pytest.raises(InputError, match="records database"):
                atomic_write(victim, b"a lot page")
    assert not any(tmp_path.iterdir())


def test_no_write_replaces_a_sqlite_database_anywhere(tmp_path):
    db = _db(tmp_path / "x.html", [make_record("M-1")])  # a database under any name
    with pytest.raises(InputError, match="SQLite database"):
        atomic_write(db, "<html>")
    assert db.read_bytes().startswith(b"SQLite format 3\0")


# ------------------------------------------------------------------------------------------ class 5

SELECTIONS = {
    "none": [],
    "one": [make_record("M-1")],
    "all refused": [make_record(f"M-{i}", refused=("wrong_serial",)) for i in range(3)],
    "all master": [make_record("MASTER", kind="master", started=f"2026-11-22T1{i}:00:00.000+00:00") for i in range(3)],
    "all simulated": [make_record(f"S-{i}", kind="simulated") for i in range(3)],
    "all restore": [make_record("M-1", kind="restore")],
    "one error": [make_record("M-1", error_step="fit")],
}


@pytest.mark.slow  # the lot page's figures: 1-2 s a selection
@pytest.mark.parametrize("selection", sorted(SELECTIONS))
@pytest.mark.parametrize("kind", ["production", "all"])
def test_the_lot_page_and_the_statistics_take_any_selection(tmp_path, selection, kind):
    db = _db(tmp_path / "r.sqlite", SELECTIONS[selection])
    for args in (["lot", "report", "--db", str(db), "-o", str(tmp_path / "lot.html"), "--kind", kind],
                 ["lot", "stats", "--db", str(db), "--kind", kind, "--json"],
                 ["records", "--db", str(db), "--plot", str(tmp_path / "r.png")]):
        res = CliRunner().invoke(cli, args)
        assert res.exit_code in (0, 1) and (res.exception is None or isinstance(res.exception, SystemExit)), \
            (args, res.output, res.exception)
        assert "Traceback" not in res.output
    assert (tmp_path / "lot.html").read_text().count("first-pass yield") >= 1


def test_the_session_counts_runs_and_motors_apart():
    from eol_cal.station.operator_session import SessionTally

    tally = SessionTally()
    for serial in ("M-1", "M-2", "M-3", "M-2"):  # three motors, one re-tested
        tally.add(make_record(serial), None)
    assert tally.summary().startswith("4 run(s) of 3 motor(s): 4 pass")
    master = SessionTally()
    for _ in range(25):
        master.add(make_record("MASTER", kind="master"), None)
    assert master.counts()["motors"] == 1 and master.counts()["runs"] == 25
