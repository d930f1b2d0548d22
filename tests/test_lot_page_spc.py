"""The lot page with SPC in headless Chromium: n and the minimum n, capability per variant and
station, the phases on the circle, a frozen baseline drawn on the control charts and the runs
that break one of Nelson's rules listed and ringed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.lot.baseline import group_lines, make_baseline
from eol_cal.lot.runs import from_records
from eol_cal.lot.spc import CIRCULAR
from eol_cal.sim.run_records import make_record
from test_report_pages import LIMITS


def _records():
    rng = np.random.default_rng(7)
    recs = []
    for day, drift in ((20, 0.0), (21, 0.0), (22, 1.5e-4)):
        for i in range(30):
            k6 = float(1.0e-3 + 5e-5 * np.clip(rng.standard_normal(), -1.8, 1.8))
            station = f"L1-S{1 + i % 2}"
            if station == "L1-S1" and i >= 10:
                k6 += drift  # station 1 drifts up on the 22nd
            recs.append(make_record(f"M{day}{i:03d}", started=f"2026-11-{day}T{6 + i // 3:02d}:{20 * (i % 3):02d}:00.000+00:00",
                                    station=station, variant="T", limits=dict(LIMITS.values), k6=k6, pp_before=5.0,
                                    pp_after=0.9 + 0.02 * (i % 5),
                                    phase_c6=math.pi - 0.05 if i % 2 else -math.pi + 0.04))  # across the wrap
    return recs


@pytest.mark.slow
def test_lot_page_with_a_baseline_in_chromium(tmp_path):
    from _chromium import Chromium, element_sizes
    from playwright.sync_api import expect

    from eol_cal.lot.lot_page import write_lot_page

    recs = _records()
    base_runs = [r for r in recs if r.started_at < "2026-11-22"]
    lot = from_records(base_runs)
    baseline = make_baseline("nov-wk47", group_lines(lot.values, lot.variant, lot.station, CIRCULAR, 25), len(base_runs),
                             {"until": "2026-11-21"})
    judged = [r for r in recs if r.started_at >= "2026-11-22"]
    page = write_lot_page(judged, tmp_path / "lot.html", title="lot.sqlite", filters={"since": "2026-11-22"}, min_n=10,
                          baseline=baseline)
    with Chromium() as b:
        log = b.open(page.as_uri())
        p = b.page
        expect(p.locator("#baseline")).to_contain_text("nov-wk47")
        text = p.locator("#baseline").text_content()
        rows = p.locator("tr.violation-row").evaluate_all(
            "rs => rs.map(r => [r.dataset.rule, r.dataset.key, r.cells[3].textContent])")
        ringed = p.locator('[id="control-L1-S1-rule-k6"] title').all_text_contents()
        frozen_ucl = p.locator("[id^=control-L1-S][id$=-cl-k6-ucl]").count()
        phase = p.locator("tr.quantity-row[data-key=phase_c6]").evaluate("r => Array.from(r.cells, c => c.textContent)")
        groups = p.locator("tr.capability-row[data-key=k6]").evaluate_all(
            "rs => rs.map(r => [r.dataset.station, r.querySelector('td.cpk').textContent])")
        card = p.locator("#card-violations").text_content()
        polar = p.locator('[id="histograms-hist-phase_c6"]').count()
        sizes = element_sizes(b.page, "svg.plot")
    assert log.console_errors == [] and set(log.requests) == {page.as_uri()} and b.left_behind == []
    assert "nov-wk47" in text and "60 runs" in text and "k6, pp_after_pct" in text
    # station 1's drift breaks rules, station 2 breaks none
    assert rows and {st for _r, _k, st in rows} == {"L1-S1"} and {k for _r, k, _s in rows} == {"k6"}
    assert "2" in {r for r, _k, _s in rows}  # 9 in a row above: Nelson's rule 2
    assert ringed and all(t.startswith("M22") and "rule" in t for t in ringed)
    assert frozen_ucl == 2 and card == str(len(rows))
    # phase_c6 at -177.7 / +177.1 deg: circular mean near 180 deg, circular sd a few degrees
    assert "(on the circle)" in phase[0] and abs(abs(float(phase[3])) - 180) < 2 and float(phase[4]) < 5
    assert phase[5] == "-" and phase[6] == "-"  # no min, no percentiles on the circle
    # capability per variant and station: 30 runs in the lot (Cpk), 15 per station (Cpk from min n 10)
    assert [st for st, _c in groups] == ["", "L1-S1", "L1-S2"] and all(c[0].isdigit() for _s, c in groups)
    assert polar == 1 and all(s["w"] > 100 for s in sizes)
