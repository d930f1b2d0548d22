"""`eol-cal msa type1` on both backends: a master motor's recorded runs give the study the pure
function gives, the reference from a declared run, the page and the PNG plots; refusals."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
import cli.common as cli_common
from cli.main import cli
from eol_cal.msa.type1 import type1_study
from eol_cal.schemas import validator
from eol_cal.records.write import insert_records

# the master's k6 in mN*m/A, run by run: 8 x 0.640, 9 x 0.642, 8 x 0.644 (the hand-worked set of
# test_msa_type1 scaled: x_ref 0.640, T = max_k6 - 0 = 1.0 -> Cg = 0.2 / (4 s), s = 0.002 sqrt(2/3))
K6 = [0.640] * 8 + [0.642] * 9 + [0.644] * 8


def rec(serial: str, i: int, k6_mnm: float, phase_deg: float = 179.5):
    t = f"2026-11-22T{8 + i // 60:02d}:{i % 60:02d}:00.000+00:00"
    return make_record(serial, started=t, station="EOL-1", variant="EPS-STD",
                       limits={"max_k6": 1.0e-3, "max_pp_after_pct": 2.0, "max_pp_before_pct": 8.0},
                       k6=k6_mnm * 1e-3, phase_k6=math.radians(phase_deg), c6=0.038 + 1e-4 * (i % 3),
                       pp_before=3.0 + 0.01 * (i % 5), pp_after=0.9 + 0.01 * (i % 4))


@pytest.mark.slow  # ~9 s on a quiet machine (CONTRIBUTING.md, "Fast or slow")
def test_msa_type1_of_a_master(records_db, tmp_path: Path, monkeypatch):
    master = [rec("MASTER-1", i, k, 179.5 if i % 2 else -179.5) for i, k in enumerate(K6)]
    declared = rec("MASTER-1", 100, 0.641, 179.0)  # the declared reference run (measured elsewhere, say)
    insert_records(records_db, master + [declared, rec("OTHER", 50, 0.9)])
    page, plots = tmp_path / "type1.html", tmp_path / "plots"
    res = CliRunner().invoke(cli, ["msa", "type1", "--db", str(records_db), "--serial", "MASTER-1", "--reference",
                                   "k6=0.640", "--tolerance", "phase_k6=40", "--json", "-o", str(page),
                                   "--plots", str(plots), "--reference-run", declared.run_id])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    validator("msa-type1").validate(doc)
    assert doc["schema"] == "eol-cal/msa-type1/1" and doc["serial"] == "MASTER-1" and doc["runs"] == 25
    k6 = next(q for q in doc["quantities"] if q["key"] == "k6")
    s = 0.002 * math.sqrt(2 / 3)
    assert k6["reference"] == 0.640 and k6["reference_source"] == "given"  # --reference over the declared run's
    assert k6["tolerance"] == pytest.approx(1.0) and k6["tolerance_source"] == "max_k6 - 0 (natural zero)"
    assert k6["sd"] == pytest.approx(s, rel=1e-6) and k6["bias"] == pytest.approx(0.002, rel=1e-6)
    assert k6["cg"] == pytest.approx(0.2 / (4 * s), rel=1e-6) and k6["cgk"] == pytest.approx((0.1 - 0.002) / (2 * s), rel=1e-6)
    assert k6["capable"] is True
    # phase_k6 across the wrap against the declared run's 179 deg; the same figures as the pure function
    ph = next(q for q in doc["quantities"] if q["key"] == "phase_k6")
    ref = type1_study(np.array([r.value("phase_k6") for r in master]), math.radians(179.0),
                      math.radians(40.0), circular=True)
    assert ph["reference"] == pytest.approx(179.0) and ph["mean"] == pytest.approx(math.degrees(ref.mean))
    assert ph["reference_source"] == f"run {declared.run_id}"
    assert ph["cg"] == pytest.approx(ref.cg.value) and ph["cgk"] == pytest.approx(ref.cgk.value)
    c6 = next(q for q in doc["quantities"] if q["key"] == "c6")
    assert c6["cg"] is None and c6["cg_reason"] == "no tolerance" and c6["tolerance_source"].startswith("no tolerance")
    assert doc["capable"] is True
    html = page.read_text()
    assert 'id="verdict"' in html and "CAPABLE" in html and "(0.1 T - |bias|) / (2 s)" in html
    if str(records_db).startswith("postgresql"):
        return _in_chromium(page, plots, doc)
    assert sorted(p.name for p in plots.iterdir()) == sorted(f"type1-{q['key']}.png" for q in doc["quantities"])
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in plots.iterdir())
    # six sigma; without --reference-run the declared run is one of the master's 26
    res = CliRunner().invoke(cli, ["msa", "type1", "--db", str(records_db), "--serial", "MASTER-1", "--reference",
                                   "k6=0.640", "--sigmas", "6", "--json"])
    s26 = np.std(K6 + [0.641], ddof=1)
    assert json.loads(res.stdout)["quantities"][0]["cg"] == pytest.approx(0.2 / (6 * s26), rel=1e-6)
    # fewer runs than the minimum: the table output and its exit code (at the log width, whatever $COLUMNS
    # the worker started with: a narrower table folds the reason across lines)
    monkeypatch.setattr(cli_common.console, "width", cli_common.LOG_WIDTH)
    res = CliRunner().invoke(cli, ["msa", "type1", "--db", str(records_db), "--serial", "OTHER"])
    assert res.exit_code == 1 and "n = 1 < 25" in res.output and "NOT shown capable" in res.output


@pytest.mark.parametrize("args, message", [
    (["--reference", "k7=1"], "'--reference'"),
    (["--tolerance", "k6=-1"], "positive"),
    (["--tolerance", "k6=x"], "not a number"),
    (["--reference-run", "nope"], "no such run"),
    (["--serial", "NOBODY"], "no master or production run of 'NOBODY'"),  # exited 1, as if studied
])
def test_msa_type1_refuses_bad_options(tmp_path: Path, args, message):
    db = tmp_path / "r.sqlite"
    other = rec("OTHER", 1, 0.9)
    insert_records(db, [rec("M", 0, 0.64), other])
    res = CliRunner().invoke(cli, ["msa", "type1", "--db", str(db), "--serial", "M", *args])
    assert res.exit_code == 2 and message in res.output
    # another motor's run is no reference of this one
    res = CliRunner().invoke(cli, ["msa", "type1", "--db", str(db), "--serial", "M", "--reference-run", other.run_id])
    assert res.exit_code == 2 and "is a run of OTHER, not of the master M" in res.output


def _in_chromium(page: Path, plots: Path, doc: dict) -> None:
    """The study's page offline in headless Chromium: five run charts with a point per run, the
    verdict, each index or its reason."""
    from _chromium import Chromium, element_sizes
    from playwright.sync_api import expect

    with Chromium() as b:
        log = b.open(page.as_uri())
        expect(b.page.locator("#verdict")).to_have_text("CAPABLE")
        sizes = element_sizes(b.page, "svg.plot")
        rows = b.page.locator("tr.study-row")
        cells = {rows.nth(i).get_attribute("data-key"): rows.nth(i).locator("td.cg").text_content()
                 for i in range(rows.count())}
        expect(b.page.locator('[id="type1-k6-values-k6"] title')).to_have_count(25)
    assert log.console_errors == [] and set(log.requests) == {page.as_uri()}
    assert b.left_behind == []
    assert [s["id"] for s in sizes] == [f"fig-type1-{q['key'].replace('_', '-')}" for q in doc["quantities"]]
    assert all(s["w"] > 100 and s["h"] > 50 for s in sizes)
    assert cells["c6"] == "no tolerance" and float(cells["k6"]) == pytest.approx(doc["quantities"][0]["cg"], rel=1e-2)
