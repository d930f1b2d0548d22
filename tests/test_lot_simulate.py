"""`eol-cal lot simulate`: motors drawn from a spread, each through the station's cycle on the plant
in-process, recorded as runs of kind simulated; kept out of the production statistics; resumable without a
motor twice; two lots compared with `lot diff --lot`; on a real distributed.LocalCluster."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.errors import InputError
from eol_cal.sim.plant_instruments import plant_instruments
from eol_cal.station.whatif import recorded_runs, simulate_batch
from eol_cal.station.whatif_plan import LotPlan
from eol_cal.schemas import validator
from eol_cal.records.record import RunRecord
from eol_cal.records.write import insert_records
from eol_cal.records.query import query_records

LIMITS = Path(__file__).resolve().parent.parent / "fixtures" / "limits.toml"
# a short calibration profile: two loads forward and one reverse, enough for k6, c6 and the delay
PROFILE = """
name = "short"
[[segment]]
speed_rpm = 60.0
iq = 20.0
seconds = 1.0
[[segment]]
speed_rpm = 60.0
iq = 65.0
seconds = 1.2
ramp_s = 0.1
[[segment]]
speed_rpm = -60.0
iq = -65.0
seconds = 1.4
ramp_s = 0.3
"""


# The Dask workers inherit the suite's JAX cache (tests/conftest.py: its own directory, never ~/.cache):
# with the cache off they compiled the plant and the fit again in each worker, ~60 of the module's
# ~85 CPU s (2026-11-29)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("lotsim")
    (d / "short.toml").write_text(PROFILE)
    strict = d / "strict.toml"  # the compensated p-p limit at 0.5 %: most motors fail it
    strict.write_text(LIMITS.read_text().replace("max_pp_after_pct = 2.0", "max_pp_after_pct = 0.5", 1))
    mech1 = d / "mech1.toml"  # the order-1 amplitude left compensated judged too, as a station judges it
    mech1.write_text(LIMITS.read_text().replace("[variant.EPS-STD]\n", "[variant.EPS-STD]\nmax_mech1_after_nm = 1.0\n", 1))
    return {"profile": d / "short.toml", "strict": strict, "mech1": mech1}


def _plan(files: dict[str, Path], name: str = "T", limits: Path = LIMITS, motors: int = 3) -> LotPlan:
    return LotPlan(name, "default", str(limits), "EPS-STD", motors, seed=5, profile=str(files["profile"]), batch=2)


@pytest.fixture(scope="module")
def batch(files) -> list[RunRecord]:
    plan = _plan(files, limits=files["mech1"])
    return [RunRecord.from_json(d) for d in simulate_batch(plan, [0, 1], plant_instruments)]


def test_a_batch_is_the_station_cycle_in_simulation(batch: list[RunRecord], files):
    assert [r.serial for r in batch] == ["T-000000", "T-000001"]
    for r in batch:
        assert r.kind == "simulated" and r.station.id == "sim:T" and r.verdict in ("pass", "fail")
        # the production steps, through the station's executor (tests/test_whatif_same_record.py: the same record)
        assert [s.step for s in r.steps] == ["pre-flight", "prepare ECU", "acquire", "fit", "table", "flash",
                                             "acquire compensated", "metrics", "report"]
        assert [b.role for b in r.blocks] == ["prepare", "calibrated"] and r.blocks[1].estimator == "best"
        assert {c.key for c in r.checks} >= {"max_k6", "max_pp_after_pct", "min_improvement_pct"}
        # the ripple judged by the station's own step function: the order 1 left is measured, as on a line
        (mech1,) = [c for c in r.checks if c.key == "max_mech1_after_nm"]
        assert math.isfinite(mech1.value) and mech1.passed is True
        # the ripple before is the calibration capture's at the operating point, after with the block
        assert r.metrics.before.pp_pct > 1.5 > r.metrics.after.pp_pct > 0.0
        assert r.station.extra["simulated"]["spread_seed"] in (5, 6)
        # the fit finds the drawn motor's k6 (the truth is in the record)
        assert r.value("k6") == pytest.approx(r.station.extra["truth"]["k6"], rel=0.05)
    # (a motor again gives the same record: the resumed lot's test below)


@pytest.mark.parametrize("records_db", ["sqlite"], indirect=True)
def test_simulated_runs_stay_out_of_production_statistics(records_db, batch: list[RunRecord]):
    insert_records(records_db, batch)
    runner = CliRunner()
    prod = json.loads(runner.invoke(cli, ["lot", "stats", "--db", str(records_db), "--json"]).stdout)
    sim = json.loads(runner.invoke(cli, ["lot", "stats", "--db", str(records_db), "--json", "--kind", "simulated",
                                         "--station", "sim:T"]).stdout)
    validator("lot-stats").validate(sim)
    assert prod["runs"] == 0 and sim["runs"] == 2 and sim["filters"]["kind"] == "simulated"
    assert {q["key"] for q in sim["quantities"] if q["count"] == 2} >= {"k6", "pp_after_pct"}


@pytest.mark.slow  # two lots on a Dask cluster; the batch test keeps the module in the fast loop
@pytest.mark.parametrize("records_db", ["sqlite"], indirect=True)
def test_a_lot_is_resumed_without_a_motor_twice_and_refused_when_made_otherwise(records_db, files, tmp_path: Path):
    from distributed import Client

    from eol_cal.lot.cluster import RefitWorkerSetup, local_cluster
    from eol_cal.station.whatif import simulate_lot

    plan = _plan(files, "R")
    # a run stopped after its first batch: that batch's records are in the database
    first = [RunRecord.from_json(d) for d in simulate_batch(plan, [0, 1], plant_instruments)]
    insert_records(records_db, first)
    assert len(recorded_runs(records_db, plan)) == 2
    with local_cluster(2) as cluster, Client(cluster) as client:  # the cluster `eol-cal lot simulate` starts
        client.register_plugin(RefitWorkerSetup(None))
        done = []
        out = simulate_lot(plan, records_db, client, plant_instruments, on_done=done.append)
        assert (out.recorded_before, out.recorded_now, sum(done)) == (2, 1, 1) and not out.failed_batches
        again = simulate_lot(plan, records_db, client, plant_instruments)
        assert (again.recorded_before, again.recorded_now) == (3, 0)
    recs = query_records(records_db, kind="simulated")
    assert sorted(r.serial for r in recs) == ["R-000000", "R-000001", "R-000002"]
    # a motor again, in a batch of its own, is the same record: its run id follows from the lot and the motor,
    # its noise from its seed, not its batch; its figures agree to their 10th digit (the joined capture's time axis)
    (again,) = [RunRecord.from_json(d) for d in simulate_batch(plan, [1], plant_instruments)]
    assert again.run_id == first[1].run_id and again.verdict == first[1].verdict
    assert again.value("k6") == pytest.approx(first[1].value("k6"), rel=1e-8)
    # the same name with other settings is another lot: refused, naming the difference
    with pytest.raises(InputError) as exc:
        recorded_runs(records_db, _plan(files, "R", limits=files["strict"]))
    assert exc.value.field == "--lot" and "limits" in exc.value.reason


@pytest.mark.slow  # two lots on a Dask cluster through the CLI
@pytest.mark.parametrize("records_db", ["sqlite"], indirect=True)
def test_cli_simulates_two_lots_and_compares_them(records_db, files, tmp_path: Path):
    runner = CliRunner()
    common = ["lot", "simulate", "--motors", "2", "--db", str(records_db), "--profile", str(files["profile"]),
              "--seed", "5", "--workers", "1", "--json"]
    res = runner.invoke(cli, common + ["--limits", str(LIMITS), "--lot", "A"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    validator("lot-simulate").validate(doc)
    assert doc["schema"] == "eol-cal/lot-simulate/1" and doc["recorded_now"] == 2 and doc["station"] == "sim:A"
    res = runner.invoke(cli, common + ["--limits", str(files["strict"]), "--lot", "B"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(cli, ["lot", "diff", "--db", str(records_db), "--lot", "sim:A", "--lot", "sim:B", "--json"])
    assert res.exit_code == 0, res.output
    cmp = json.loads(res.stdout)
    validator("lot-compare").validate(cmp)
    a, b = cmp["lots"]
    assert cmp["compared"] == 2 and a["runs"] == b["runs"] == 2
    # the same motors (seeds 5 and 6) under a stricter compensated limit: B fails where A passes
    assert a["yield"] >= b["yield"]
    for c in cmp["changes"]:
        assert c["verdicts"] == ["pass", "fail"] and c["newly_failing"] == ["max_pp_after_pct"]
    assert len(cmp["changes"]) == round(2 * (a["yield"] - b["yield"]))
    page = tmp_path / "lot.html"
    res = runner.invoke(cli, ["lot", "report", "--db", str(records_db), "--kind", "simulated", "--station", "sim:A",
                              "-o", str(page)])
    assert res.exit_code == 0, res.output
    assert "(2 runs)" in res.output and "A-000001" in page.read_text()
    # bad input: exit 2, the option named
    res = runner.invoke(cli, common + ["--limits", str(LIMITS), "--lot", "a/b"])
    assert res.exit_code == 2 and "--lot" in res.output
