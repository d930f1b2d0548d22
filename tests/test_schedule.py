"""The suite's own schedule (tests/_schedule.py): the costliest files first, the 10 000 power-ups'
parts on both workers, every test still run, a file's tests together and in their order."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path

import _schedule

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class _Item:
    nodeid: str


def test_each_split_test_is_a_long_parametrized_test_that_exists():
    # a name that no longer matches would silently put its file back on one worker
    for entry in _schedule.SPLIT:
        path, name = entry.split("::")
        module = importlib.import_module(Path(path).stem)
        marks = {m.name for m in getattr(getattr(module, name), "pytestmark", [])}
        assert {"long", "parametrize"} <= marks, entry


def test_a_split_tests_parts_are_units_and_the_rest_of_its_file_one():
    (entry,) = _schedule.SPLIT
    path = entry.split("::")[0]
    assert _schedule.unit(f"{entry}[3]") == f"{entry}[3]"
    assert _schedule.unit(f"{path}::test_a_weak_fingerprint_fails") == path
    assert _schedule.unit("tests/test_x.py::TestA::test_b[1]") == "tests/test_x.py"


def test_the_costliest_units_go_first_and_nothing_else_moves(tmp_path, monkeypatch):
    table = tmp_path / "schedule_cpu.txt"
    table.write_text("# a comment\n  90 tests/test_c.py\n 20 tests/test_b.py::test_p[1]\n")
    monkeypatch.setattr(_schedule, "TABLE", table)
    monkeypatch.setattr(_schedule, "SPLIT", ("tests/test_b.py::test_p",))
    ids = ["tests/test_a.py::t1", "tests/test_b.py::test_p[0]", "tests/test_b.py::test_p[1]", "tests/test_b.py::t2",
           "tests/test_c.py::t1", "tests/test_c.py::t2", "tests/test_d.py::t1"]
    items = [_Item(i) for i in ids]
    _schedule.costliest_first(items)  # type: ignore[arg-type]
    assert [i.nodeid for i in items] == [
        "tests/test_c.py::t1", "tests/test_c.py::t2", "tests/test_b.py::test_p[1]",
        "tests/test_a.py::t1", "tests/test_b.py::test_p[0]", "tests/test_b.py::t2", "tests/test_d.py::t1"]


def test_the_checked_in_table_reads():
    table = _schedule.costs()
    assert table and all(seconds > 0 for seconds in table.values())
    assert all((ROOT / name.split("::")[0]).is_file() for name in table), "a unit's file is gone: regenerate the table"
