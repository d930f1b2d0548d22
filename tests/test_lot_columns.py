"""Lot statistics from the database's columns (no record JSON parsed) are the statistics of the
records themselves, on both backends; a version-2 database migrates to the current version with the new
columns filled from each row's record JSON; time order from the start-time strings."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa
from click.testing import CliRunner

from eol_cal.sim.lot_records import lot_record
from cli.main import cli
from eol_cal.errors import InputError
from eol_cal.lot.runs import QUANTITIES, from_records, read_lot, time_order
from eol_cal.lot.spc import CIRCULAR, circular_summary
from eol_cal.lot.stats import capability, first_pass_yield, imr_limits, pareto, summary
from eol_cal.lot.summary import lot_summary
from eol_cal.lot.lot_page import run_time
from eol_cal.schemas import validator
from eol_cal.records.record import RunRecord
from eol_cal.records.connect import engine
from eol_cal.records.migrations import SCHEMA_VERSION, migrate
from eol_cal.records.rows import row_values
from eol_cal.records.tables import runs
from eol_cal.records.write import insert_records
from eol_cal.records.query import query_records, read_rows, select_runs
from test_records_backends import _V1

LOT = [lot_record(i, motors=70, hi_every=25, refusals=True) for i in range(90)]


def by_definition(records: list[RunRecord], min_n: int = 25) -> dict:
    """The lot's figures record by record, straight from the definitions in eol_cal.lot.stats and
    eol_cal.lot.spc (the reading lot statistics had before the columns): the reference.
    Production runs only."""
    recs = sorted((r for r in records if r.kind == "production"), key=lambda r: (run_time(r), r.run_id))
    quantities = {}
    for q in QUANTITIES:
        x = [r.value(q.key) * q.scale for r in recs]
        by_variant = {}
        for v in sorted({r.limits.variant for r in recs}):
            rs = [r for r in recs if r.limits.variant == v]
            lims = sorted({r.limits.value(q.limit_key) for r in rs} - {None}) if q.limit_key else []
            lims = [y * q.scale for y in lims if math.isfinite(y)]
            xv = [r.value(q.key) * q.scale for r in rs]
            n = sum(1 for y in xv if math.isfinite(y))
            if len(lims) == 1 and q.key not in CIRCULAR:
                cap = capability(xv, usl=lims[0]) if q.sense == "max" else capability(xv, lsl=lims[0])
                by_variant[v] = (n, lims[0], cap if n >= min_n else None)
        circ = circular_summary([r.value(q.key) for r in recs]) if q.key in CIRCULAR else None
        quantities[q.key] = (summary(x), by_variant, circ)
    control = {}
    for st in sorted({r.station_label for r in recs}):
        rs = [r for r in recs if r.station_label == st]
        control[st] = {}
        for key, scale in (("k6", 1e3), ("pp_after_pct", 1.0)):
            y = [r.value(key) * scale for r in rs]
            n = sum(1 for v in y if math.isfinite(v))
            control[st][key] = (len(rs), n, imr_limits(y) if n >= min_n else None)
    return {"fpy": first_pass_yield(recs), "pareto": pareto(recs), "quantities": quantities, "control": control}


def _same(a: float | None, b: float) -> bool:
    return (a is None and not math.isfinite(b)) or (a is not None and a == pytest.approx(b, rel=1e-12, abs=1e-15))


def assert_matches_definition(doc: dict, ref: dict) -> None:
    assert (doc["first_pass_yield"], doc["motors"]) == (pytest.approx(ref["fpy"][0]), ref["fpy"][1])
    assert [(p["cause"], p["runs"]) for p in doc["pareto"]] == [(c, n) for c, n, _s in ref["pareto"]]
    assert [p["cumulative"] for p in doc["pareto"]] == pytest.approx([s for _c, _n, s in ref["pareto"]])
    assert [q["key"] for q in doc["quantities"]] == [q.key for q in QUANTITIES]
    for q in doc["quantities"]:
        s, by_variant, circ = ref["quantities"][q["key"]]
        assert q["count"] == s.count > 0
        if circ is not None:  # a phase: on the circle, no linear order statistics
            scale = 180 / math.pi
            assert q["circular"] and _same(q["mean"], circ.mean * scale) and _same(q["sd"], circ.sd * scale)
            assert q["min"] is None and q["max"] is None and set(q["percentiles"].values()) == {None}
            assert sum(q["histogram"]["counts"]) == circ.count
            continue
        for got, want in ((q["mean"], s.mean), (q["sd"], s.sd), (q["min"], s.minimum), (q["max"], s.maximum),
                          *((q["percentiles"][f"p{p:g}"], v) for p, v in s.percentiles.items())):
            assert _same(got, want), (q["key"], got, want)
        whole = {g["variant"]: g for g in q["capability"] if g["station"] is None}
        assert set(whole) == set(by_variant)
        for v, (n, limit, cap) in by_variant.items():
            g = whole[v]
            assert g["n"] == n and g["limit"] == pytest.approx(limit)
            if cap is None:
                assert g["cpk"] is None and g["cpk_reason"] == f"n = {n} < 25"
            else:
                assert _same(g["cpk"], cap.cpk) and _same(g["ppk"], cap.ppk) and _same(g["cp"], cap.cp)
        if len(by_variant) == 1:
            assert q["cpk"] == next(iter(whole.values()))["cpk"]
        elif by_variant:
            assert q["cpk"] is None and "mixes variants" in q["cpk_reason"]
    assert list(doc["control"]) == list(ref["control"])
    for st, qs in ref["control"].items():
        for key, (runs_, n, cl) in qs.items():
            got = doc["control"][st][key]
            assert got["runs"] == runs_ and got["n"] == n
            for name in ("center", "ucl", "lcl", "mr_center", "mr_ucl"):
                assert _same(got[name], getattr(cl, name)) if cl else got[name] is None, (st, key, name)
            assert (got["reason"] is None) == (cl is not None)


@pytest.mark.parametrize("variant", [None, "EPS-STD"])
def test_lot_stats_from_the_columns_equal_the_statistics_of_the_records(records_db, variant):
    insert_records(records_db, LOT)
    stored = query_records(records_db)  # the full parsed records, as the database returns them
    if variant:
        stored = [r for r in stored if r.limits.variant == variant]
    fast = lot_summary(read_lot(records_db, variant=variant))
    assert fast == lot_summary(from_records([r for r in stored if r.kind == "production"]))
    ref = by_definition(stored)
    assert_matches_definition(fast, ref)
    # the lot is what the test means it to be: re-tests, all verdicts, a run without station, ties,
    # every cause, capability against a limit (and none where the variants' limits differ)
    refused = [r for r in stored if r.kind == "refusal"]
    assert refused and fast["runs"] == len(stored) - len(refused) and fast["motors"] < fast["runs"]
    assert all(fast["verdicts"][v] > 0 for v in ("pass", "fail", "error"))
    assert "(no station id)" in fast["control"] and len(fast["control"]) == 7
    assert len({r.started_at for r in stored}) < len(stored)
    assert {p["cause"] for p in fast["pareto"]} >= {"max_pp_after_pct", "max_k6", "min_r2", "error in acquire"}
    k6 = next(q for q in fast["quantities"] if q["key"] == "k6")
    assert (k6["cpk"] is not None) == (variant == "EPS-STD")
    assert {g["variant"] for g in k6["capability"]} == ({"EPS-STD"} if variant else {"EPS-STD", "EPS-HI"})
    assert all(c["reason"] == f"n = {c['n']} < 25" for qs in fast["control"].values() for c in qs.values())
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(records_db), "--json"]
                             + (["--variant", variant] if variant else []))
    assert res.exit_code == 0, res.output
    printed = json.loads(res.stdout)
    validator("lot-stats").validate(printed)
    assert {k: v for k, v in printed.items() if k not in ("schema", "db", "filters", "refusals")} == fast
    # the refusals apart: their own Pareto of reasons, in no figure of the lot
    assert printed["refusals"]["runs"] == len(refused)
    assert {p["cause"]: p["runs"] for p in printed["refusals"]["pareto"]} == {
        c: sum(r.refusal_codes == (c,) for r in refused) for c in {r.refusal_codes[0] for r in refused}}


def _v2_database(db, records: list[RunRecord]) -> None:
    """A records database laid out as eol-cal wrote it at schema version 2 (no version-3 or -4 columns)."""
    eng = engine(db)
    with eng.begin() as con:
        for stmt in _V1.split(";"):
            if stmt.strip():
                con.exec_driver_sql(stmt)
        con.exec_driver_sql("ALTER TABLE runs ADD COLUMN station TEXT")
        con.exec_driver_sql("ALTER TABLE runs ADD COLUMN operator TEXT")
        con.exec_driver_sql("CREATE TABLE schema_version (version INTEGER NOT NULL)")
        con.exec_driver_sql("INSERT INTO schema_version (version) VALUES (2)")
        later = ("limits_json", "error_step", "phase_c6", "fit_r2", "fit_rms_nm", "kind", "causes")
        rows = [{k: v for k, v in row_values(r).items() if k not in later} | {"record_json": json.dumps(r.to_json())}
                for r in records]
        con.execute(runs.insert(), rows)
    if isinstance(db, Path):
        eng.dispose()


def test_a_version_2_database_migrates_with_the_new_columns_filled(records_db):
    lot = LOT[:40]
    _v2_database(records_db, lot)
    with pytest.raises(InputError, match="schema version 2.*migrate it first"):
        read_lot(records_db)
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(records_db)])
    assert res.exit_code == 2 and "schema version 2" in res.output
    assert migrate(records_db) == (2, SCHEMA_VERSION)
    new = ("limits_json", "error_step", "phase_c6", "fit_r2", "fit_rms_nm", "kind", "causes")
    got = {r["run_id"]: r for r in read_rows(records_db, select_runs())}
    for r in lot:
        want = row_values(r)
        assert {k: got[r.run_id][k] for k in new} == {k: want[k] for k in new}
    errors = [r for r in lot if r.verdict == "error" and r.kind == "production"]
    assert errors and all(got[r.run_id]["error_step"] == r.error.step for r in errors)
    assert all(got[r.run_id]["fit_r2"] is None for r in errors if r.fit is None)
    assert json.loads(got[lot[0].run_id]["limits_json"]) == {**lot[0].limits.to_dict(), "sha256": lot[0].limits_sha256}
    assert all(math.isfinite(got[r.run_id]["fit_r2"]) for r in lot if r.fit)
    assert {got[r.run_id]["kind"] for r in lot} == {"production", "refusal"}
    # the migrated database gives the statistics of its records; new records fill the columns
    assert insert_records(records_db, LOT[40:45]) == 5
    measured = [r for r in LOT[:45] if r.kind == "production"]
    assert read_lot(records_db).verdict.size == len(measured)
    doc = lot_summary(read_lot(records_db))
    r2 = next(q for q in doc["quantities"] if q["key"] == "fit_r2")
    assert r2["count"] == sum(1 for r in measured if r.fit) and r2["limit"] == pytest.approx(0.3)
    with engine(records_db, readonly=True).connect() as con:
        assert con.execute(sa.select(sa.func.count()).where(runs.c.limits_json.is_(None))).scalar() == 0


def test_time_order_is_the_order_of_the_start_strings_or_of_the_parsed_times():
    same = ["2026-11-22T08:00:01.000+00:00", "2026-11-22T08:00:00.500+00:00", "2026-11-22T08:00:00.500+00:00"]
    assert time_order(same, ["b", "z", "a"]).tolist() == [2, 1, 0]
    # other forms: an offset, no milliseconds, Z, a naive time (UTC)
    mixed = ["2026-11-22T09:30:00+01:00", "2026-11-22T08:00:00Z", "2026-11-22T08:15:00.250", "2026-11-22T08:00:00.5+00:00"]
    assert time_order(mixed, ["a", "b", "c", "d"]).tolist() == [1, 3, 2, 0]
    with pytest.raises(InputError, match="started_at"):
        time_order(["yesterday", "2026-11-22T08:00:00+00:00"], ["a", "b"])
    with pytest.raises(InputError, match="started_at.*2026-13"):  # the station's length, not a time
        time_order(["2026-13-22T08:00:00.000+00:00", "2026-11-22T08:00:00.000+00:00"], ["a", "b"])
    recs = sorted(LOT, key=lambda r: (r.started_at, r.run_id))
    lot = from_records(LOT[::-1])  # any input order: time order out
    assert lot.run_id.tolist() == [r.run_id for r in recs]
    assert np.array_equal(lot.values["k6"], np.array([r.value("k6") for r in recs]), equal_nan=True)


def test_a_corrupt_record_refuses_the_migration_and_leaves_version_2(records_db):
    lot = LOT[:5]
    _v2_database(records_db, lot)
    with engine(records_db).begin() as con:
        con.execute(runs.update().where(runs.c.run_id == lot[2].run_id).values(record_json='{"serial": '))
    with pytest.raises(InputError, match=f"run {lot[2].run_id} record_json"):
        migrate(records_db)
    # one transaction: no column added, still version 2; mended, the migration goes through
    with engine(records_db, readonly=True).connect() as con:
        assert "limits_json" not in {c["name"] for c in sa.inspect(con).get_columns("runs")}
    with engine(records_db).begin() as con:
        con.execute(runs.update().where(runs.c.run_id == lot[2].run_id).values(record_json=json.dumps(lot[2].to_json())))
    assert migrate(records_db) == (2, SCHEMA_VERSION)
