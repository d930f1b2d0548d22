"""`eol-cal lot stats` on both backends: Cpk, control limits, yield and Pareto of a small lot
against values computed by hand; filters; the CSV export."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.records.write import insert_records


def rec(serial: str, hour: int, k6_mnm: float, station: str, verdict: str = "pass", variant="EPS-STD"):
    # a failed run: its compensated p-p over the variant's 2 %
    return make_record(serial, started=f"2026-11-22T{hour:02d}:00:00.000+00:00", station=station, variant=variant,
                       limits={"max_k6": 2.0e-3, "min_improvement_pct": 10.0}, k6=k6_mnm * 1e-3,
                       pp_after=2.5 if verdict == "fail" else 1.0)


def test_lot_stats_by_hand(records_db, tmp_path: Path):
    lot = [rec("A", 8, 1.0, "EOL-1"), rec("B", 9, 1.2, "EOL-1"), rec("C", 10, 0.9, "EOL-1"),
           rec("D", 11, 1.1, "EOL-1", "fail"),
           rec("E", 12, 1.5, "EOL-2"), rec("F", 13, 1.7, "EOL-2"),
           rec("G", 14, 9.0, "EOL-3", variant="EPS-HI")]
    insert_records(records_db, lot)
    run = CliRunner().invoke
    # the default minimum n (25): no index and no limit from six runs, the reason instead
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--variant", "EPS-STD", "--json"])
    few = json.loads(res.stdout)
    k6 = next(q for q in few["quantities"] if q["key"] == "k6")
    assert few["min_n"] == 25 and k6["cpk"] is None and k6["cpk_reason"] == "n = 6 < 25"
    assert few["control"]["EOL-1"]["k6"]["ucl"] is None and few["control"]["EOL-1"]["k6"]["reason"] == "n = 4 < 25"
    # a minimum of 4 (the hand-worked figures)
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--variant", "EPS-STD", "--json", "--min-n", "4",
                    "--csv", str(tmp_path / "runs.csv")])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["runs"] == 6 and doc["verdicts"] == {"pass": 5, "fail": 1, "error": 0}
    assert doc["first_pass_yield"] == pytest.approx(5 / 6)
    assert doc["pareto"] == [{"cause": "max_pp_after_pct", "runs": 1, "cumulative": 1.0}]
    k6 = next(q for q in doc["quantities"] if q["key"] == "k6")
    x = [1.0, 1.2, 0.9, 1.1, 1.5, 1.7]  # mN*m/A in time order
    mean = sum(x) / 6  # 1.2333
    mr_bar = (0.2 + 0.3 + 0.2 + 0.4 + 0.2) / 5  # 0.26
    sigma_w = mr_bar / 1.128
    assert k6["count"] == 6 and k6["mean"] == pytest.approx(mean) and k6["limit"] == pytest.approx(2.0)
    assert k6["cpk"] == pytest.approx((2.0 - mean) / (3 * sigma_w))  # 0.7667 / 0.6915
    assert k6["cpk"] == pytest.approx(1.1087, abs=1e-4)
    assert k6["cp"] is None and k6["cp_reason"] == "needs both limits"  # one-sided limit
    # per variant and station: EOL-1 (1.0, 1.2, 0.9, 1.1: mean 1.05, MRbar 0.7/3) and EOL-2 (two runs)
    groups = {(g["variant"], g["station"]): g for g in k6["capability"]}
    assert set(groups) == {("EPS-STD", None), ("EPS-STD", "EOL-1"), ("EPS-STD", "EOL-2")}
    assert groups[("EPS-STD", None)]["cpk"] == k6["cpk"] and groups[("EPS-STD", None)]["n"] == 6
    assert groups[("EPS-STD", "EOL-1")]["cpk"] == pytest.approx((2.0 - 1.05) / (3 * (0.7 / 3) / 1.128))
    assert groups[("EPS-STD", "EOL-2")]["cpk"] is None and groups[("EPS-STD", "EOL-2")]["cpk_reason"] == "n = 2 < 4"
    cl1 = doc["control"]["EOL-1"]["k6"]
    mr1 = (0.2 + 0.3 + 0.2) / 3
    assert cl1["runs"] == 4 and cl1["n"] == 4 and cl1["center"] == pytest.approx(1.05)
    assert cl1["ucl"] == pytest.approx(1.05 + 2.66 * mr1, abs=2e-4) and cl1["lcl"] == pytest.approx(1.05 - 2.66 * mr1, abs=2e-4)
    assert cl1["mr_center"] == pytest.approx(mr1) and cl1["mr_ucl"] == pytest.approx(3.267 * mr1)
    assert set(doc["control"]) == {"EOL-1", "EOL-2"} and doc["control"]["EOL-2"]["k6"]["reason"] == "n = 2 < 4"
    # the whole lot mixes two variants: capability per variant, never across them
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--json", "--min-n", "2"])
    mixed = next(q for q in json.loads(res.stdout)["quantities"] if q["key"] == "k6")
    assert mixed["cpk"] is None and "mixes variants" in mixed["cpk_reason"]
    assert {(g["variant"], g["station"]) for g in mixed["capability"]} >= {("EPS-HI", None), ("EPS-STD", None)}
    assert next(g for g in mixed["capability"] if g["variant"] == "EPS-HI")["cpk_reason"] == "n = 1 < 2"
    with open(tmp_path / "runs.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["serial"] for r in rows] == list("ABCDEF") and rows[1]["station"] == "EOL-1"
    assert float(rows[4]["k6 [mN*m/A]"]) == pytest.approx(1.5)  # one unit per quantity: the one people read
    assert "phase_k6 [deg]" in rows[0] and "pp_after_pct [%]" in rows[0] and rows[3]["kind"] == "production"
    # filters: one station, a day range with nothing in it; the table output
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--station", "EOL-2", "--json"])
    assert json.loads(res.stdout)["runs"] == 2
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--since", "2026-11-23", "--json"])
    assert json.loads(res.stdout)["runs"] == 0
    res = run(cli, ["lot", "stats", "--db", str(records_db)])
    assert res.exit_code == 0 and "first-pass yield" in res.output and "EOL-3" in res.output
    assert "n = 4 < 25" in res.output
