"""The baseline store on SQLite and on a real PostgreSQL server: frozen lines per quantity,
variant and station stored once, read back in another connection and judged against."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sqlalchemy as sa

from eol_cal.errors import InputError
from eol_cal.lot.baseline import NO_VARIANT, group_lines, list_baselines, load, make_baseline, store
from eol_cal.lot.spc import judge
from eol_cal.schemas import validator
from eol_cal.records.connect import engine
from eol_cal.records.migrations import SCHEMA_VERSION, migrate as migrate_records
from eol_cal.records.write import insert_records


def _lines():
    rng = np.random.default_rng(3)
    n = 60
    station = np.array(["EOL-1", "EOL-2"] * (n // 2), dtype=object)
    variant = ["EPS-STD"] * (n - 4) + [None] * 4  # four runs without a variant: too few for limits
    k6 = 6.4e-4 + 2e-5 * rng.standard_normal(n)
    phase = np.pi - 0.02 + 0.01 * rng.standard_normal(n)  # near the wrap: some values come out near -pi
    phase = np.where(phase > np.pi, phase - 2 * np.pi, phase)
    return group_lines({"k6": k6, "phase_c6": phase}, variant, station, circular={"phase_c6"}, min_n=25), k6, station


def test_baseline_stored_and_reused(records_db):
    migrate_records(records_db)  # an existing records database (a SQLite file is not made by a baseline)
    lines, k6, station = _lines()
    b = make_baseline("shift-1", lines, runs=60, filters={"since": "2026-11-02", "until": "2026-11-03"})
    store(records_db, b)
    got = load(records_db, "shift-1")
    assert got.runs == 60 and got.min_n == 25 and got.filters["since"] == "2026-11-02" and got.filters["variant"] is None
    assert set(got.lines) == set(lines)
    one = got.line("k6", "EPS-STD", "EOL-1")
    ref = lines[("k6", "EPS-STD", "EOL-1")]
    assert one.n == 28 and one.center == ref.center and one.sigma == ref.sigma and one.mr_center == ref.mr_center
    x1 = k6[:-4][station[:-4] == "EOL-1"]
    assert one.center == pytest.approx(float(x1.mean()))
    assert one.sigma == pytest.approx(float(np.abs(np.diff(x1)).mean()) / 1.128)
    few = got.line("k6", None, "EOL-2")
    assert few.center is None and few.reason == "n = 2 < 25" and got.lines[("k6", NO_VARIANT, "EOL-2")] == few
    ph = got.line("phase_c6", "EPS-STD", "EOL-2")
    assert ph.circular and abs(abs(ph.center) - (math.pi - 0.02)) < 0.01  # the circular mean, near pi
    # a new run 5 sigma above the frozen centre fires rule 1; a phase across the wrap from it does not
    v = judge([one.center + 5 * one.sigma], one, "k6")
    assert [(x.rule, x.side) for x in v] == [(1, 1)]
    assert judge([ph.center + 2 * np.pi - 0.001], ph) == []
    # the same name again is refused; --replace makes it anew; listing
    with pytest.raises(InputError, match="exists already"):
        store(records_db, b)
    store(records_db, make_baseline("shift-1", {}, runs=0, filters={}), replace=True)
    assert load(records_db, "shift-1").lines == {} and [r["name"] for r in list_baselines(records_db)] == ["shift-1"]
    with pytest.raises(InputError, match=r"not found \(there are: shift-1\)"):
        load(records_db, "shift-9")
    assert migrate_records(records_db) == (SCHEMA_VERSION, SCHEMA_VERSION)


def test_baseline_tables_refuse_a_newer_layout_and_a_missing_database(records_db, tmp_path):
    insert_records(records_db, [])  # a records database made by its first record: every table, no baseline
    assert list_baselines(records_db) == []
    eng = engine(records_db)
    with eng.begin() as con:
        con.execute(sa.text("UPDATE schema_version SET version = 99"))
    if not str(records_db).startswith("postgresql"):
        eng.dispose()
    with pytest.raises(InputError, match="newer than this tool"):
        store(records_db, make_baseline("b", {}, runs=0, filters={}))
    with pytest.raises(InputError, match="newer than this tool"):
        load(records_db, "b")
    with pytest.raises(InputError, match="database not found"):
        load(tmp_path / "none.sqlite", "b")
    with pytest.raises(InputError, match="holds no baselines"):
        migrate_records(tmp_path / "r.sqlite")
        load(tmp_path / "r.sqlite", "b")


def test_lot_baseline_command(records_db):
    import json

    from click.testing import CliRunner

    from eol_cal.sim.lot_records import lot_record
    from cli.main import cli

    recs = [lot_record(i, motors=60, stations=2) for i in range(80)]
    insert_records(records_db, recs)
    # every 13th run has no station id (7 runs, one an error run without values): too few for limits
    n_none = sum(1 for i, r in enumerate(recs) if i % 13 == 0 and math.isfinite(r.value("k6")))
    run = CliRunner().invoke
    res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "nov", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    validator("lot-baseline").validate(doc)
    assert doc["schema"] == "eol-cal/lot-baseline/1" and doc["runs"] == 80 and doc["min_n"] == 25
    k6 = {(x["variant"], x["station"]): x for x in doc["lines"] if x["quantity"] == "k6"}
    none = k6[("EPS-STD", "(no station id)")]
    assert n_none == 6 and none["reason"] == "n = 6 < 25" and none["ucl"] is None
    e0 = k6[("EPS-STD", "EOL-0")]
    assert e0["n"] >= 25 and e0["unit"] == "mN*m/A" and e0["ucl"] == pytest.approx(e0["center"] + 3 * e0["sigma"])
    assert 0.58 < e0["center"] < 0.70  # lot_record's k6: 0.64 +- 0.06 mN*m/A
    stored = load(records_db, "nov").line("k6", "EPS-STD", "EOL-0")
    assert stored.center * 1e3 == pytest.approx(e0["center"]) and stored.n == e0["n"]
    ph = {(x["variant"], x["station"]): x for x in doc["lines"] if x["quantity"] == "phase_k6"}[("EPS-STD", "EOL-0")]
    assert ph["circular"] and ph["unit"] == "deg"
    # the same name again: refused (exit 2, one line); --replace; a period without runs; too few everywhere
    res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "nov"])
    assert res.exit_code == 2 and "exists already" in res.output
    assert run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "nov", "--replace"]).exit_code == 0
    res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "dec", "--since", "2027-01-01"])
    assert res.exit_code == 2 and "no runs selected" in res.output
    res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "dec", "--min-n", "100"])
    assert res.exit_code == 2 and "nothing stored" in res.output and "n = " in res.output
    assert [b["name"] for b in list_baselines(records_db)] == ["nov"]
