"""The golden scenarios computed in spawned processes (:func:`eol_cal.firmware.vectors.scenario_rows_in_parallel`):
every name's own result, in the names' order, whether one core or several compute them."""

from __future__ import annotations

import pytest

from eol_cal.firmware import vectors


@pytest.mark.slow  # spawns two interpreters (where there are two cores)
def test_each_scenario_gets_its_own_rows_in_the_given_order():
    names = ["b.csv", "a.csv", "long.csv", "c.csv"]
    got = vectors.scenario_rows_in_parallel(str.upper, names, seconds=len)
    assert list(got) == names
    assert got == {n: n.upper() for n in names}


def test_one_core_computes_them_here(monkeypatch):
    monkeypatch.setattr(vectors.os, "sched_getaffinity", lambda pid: {0})
    calls = []

    def rows_of(name):  # not picklable: would fail in a pool
        calls.append(name)
        return [[name]]

    got = vectors.scenario_rows_in_parallel(rows_of, ["x", "y"], seconds=len)
    assert got == {"x": [["x"]], "y": [["y"]]} and calls == ["x", "y"]
