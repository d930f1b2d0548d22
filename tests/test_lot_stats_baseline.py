"""`lot baseline` then `lot stats --baseline` twice on both backends: the frozen lines are
reused as stored (not recomputed from the runs judged), a quiet period passes (exit 0), a drift
fires the rules (exit 1) with its rule, runs and quantity in the JSON, the CSV and the table."""

from __future__ import annotations

import csv
import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.schemas import validator
from eol_cal.records.write import insert_records

T0 = dt.datetime(2026, 11, 2, 6, 0, tzinfo=dt.UTC)


def rec(i: int, day: int, k6_mnm: float, station: str):
    t = (T0 + dt.timedelta(days=day, minutes=3 * i)).isoformat(timespec="milliseconds")
    return make_record(f"M{day}-{i:04d}", started=t, station=station, variant="EPS-STD",
                       limits={"max_k6": 1.2e-3, "max_pp_after_pct": 2.0}, k6=k6_mnm * 1e-3,
                       phase_c6=np.pi - 0.01 * (i % 3), pp_after=0.9 + 0.05 * ((i * 7) % 5 - 2))


def period(day: int, n: int, seed: int, shift: float = 0.0, drift_from: int | None = None):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        k6 = 0.640 + 0.010 * float(np.clip(rng.standard_normal(), -1.9, 1.9))  # never beyond 2 sigma by itself
        if drift_from is not None and i >= drift_from:
            k6 += shift
        out.append(rec(i, day, k6, "EOL-1"))
    return out


@pytest.mark.slow  # ~3 s on a quiet machine (CONTRIBUTING.md, "Fast or slow")
def test_baseline_judges_two_later_lot_stats_calls(records_db, tmp_path: Path):
    run = CliRunner().invoke
    insert_records(records_db, period(0, 40, 1))
    res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "wk45", "--until", "2026-11-02", "--json"])
    assert res.exit_code == 0, res.output
    base = {(x["quantity"], x["station"]): x for x in json.loads(res.stdout)["lines"]}
    k6_line = base[("k6", "EOL-1")]
    assert k6_line["n"] == 40 and k6_line["reason"] is None
    # a quiet later period (alternating about the centre: no rule can fire): exit 0, judged against the stored line
    quiet = [rec(i, 1, k6_line["center"] + (-0.5 if i % 2 else 0.5) * k6_line["sigma"], "EOL-1") for i in range(20)]
    insert_records(records_db, quiet)
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--since", "2026-11-03", "--baseline", "wk45", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["baseline"]["name"] == "wk45" and doc["violations"] == []
    judged = {j["quantity"]: j for j in doc["judged"]}
    assert set(judged) == {"k6", "pp_after_pct"}
    assert judged["k6"]["center"] == pytest.approx(k6_line["center"]) and judged["k6"]["sigma"] == pytest.approx(k6_line["sigma"])
    assert judged["k6"]["runs"] == 20 and judged["k6"]["baseline_n"] == 40
    # a drifting period: the 9th run on one side fires Nelson's rule 2, a jump of 4 sigma rule 1
    drifting = [rec(i, 2, k6_line["center"] + (1.5 + 0.1 * (i % 2)) * k6_line["sigma"], "EOL-1") for i in range(8)]
    drifting.append(rec(8, 2, k6_line["center"] + 4.0 * k6_line["sigma"], "EOL-1"))
    insert_records(records_db, drifting)
    csv_path = tmp_path / "runs.csv"
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--since", "2026-11-03", "--baseline", "wk45", "--json",
                    "--csv", str(csv_path)])
    assert res.exit_code == 1, res.output
    doc = json.loads(res.stdout)
    validator("lot-stats").validate(doc)
    judged = {j["quantity"]: j for j in doc["judged"]}
    assert judged["k6"]["center"] == pytest.approx(k6_line["center"])  # the stored line, not the drifted runs' mean
    fired = {(v["quantity"], v["rule"]): v for v in doc["violations"]}
    ids = [r.run_id for r in drifting]
    assert fired[("k6", 1)]["runs"] == [ids[8]] and fired[("k6", 1)]["side"] == "above"
    assert fired[("k6", 2)]["runs"] == ids and fired[("k6", 2)]["station"] == "EOL-1"
    assert fired[("k6", 6)]["runs"][:4] == ids[:4]  # 4 of 5 beyond 1 sigma from the first four on
    # 1.5-1.6 sigma, then one point at 4 sigma: never 2 of 3 beyond 2 sigma; alternating: no trend
    assert ("k6", 5) not in fired and ("k6", 3) not in fired
    assert fired[("k6", 2)]["serials"] == [r.serial for r in drifting] and fired[("k6", 2)]["values"][0] > k6_line["center"]
    with open(csv_path, newline="") as f:
        rows = {r["run_id"]: r for r in csv.DictReader(f)}
    assert rows[ids[8]]["rules"] == "k6:1;k6:2;k6:6" and rows[quiet[0].run_id]["rules"] == ""
    assert rows[ids[0]]["rules"] == "k6:2;k6:6"
    # the table output names the rule and ends with exit 1
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--since", "2026-11-04", "--baseline", "wk45"])
    assert res.exit_code == 1 and "rule 2: 9 points in a row" in res.output and "rule violation(s) (exit 1)" in res.output
    # the lot page of the same period against the same baseline lists the same violations
    page = tmp_path / "lot.html"
    res = run(cli, ["lot", "report", "--db", str(records_db), "--since", "2026-11-03", "--baseline", "wk45", "-o", str(page)])
    assert res.exit_code == 0, res.output
    html = page.read_text()
    assert html.count('class="violation-row"') == len(doc["violations"]) and "baseline <b>wk45</b>" in html
    # a baseline that is not there; --quantity without --baseline; a phase judged on the circle
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--baseline", "wk99"])
    assert res.exit_code == 2 and "not found (there are: wk45)" in res.output
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--quantity", "k6"])
    assert res.exit_code == 2 and "--baseline" in res.output
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--since", "2026-11-03", "--until", "2026-11-03",
                    "--baseline", "wk45", "--quantity", "phase_c6", "--json"])
    assert res.exit_code == 0, res.output
    ph = json.loads(res.stdout)["judged"][0]
    assert ph["quantity"] == "phase_c6" and ph["circular"] and abs(abs(ph["center"]) - 179.4) < 0.5
