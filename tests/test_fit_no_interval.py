"""Where a quantity cannot be given an honest interval it gets none, and says why (issue 34, item 4).

The mechanical orders' interval rests on the segments' scatter (the delete-one-segment jackknife,
Student's t with S - 1 degrees of freedom): a fit of two segments had one degree of freedom and
reported order 1 as +-54 N*m (the typed golden ``one_load``). From fewer than
:data:`~eol_cal.analysis.fit.mech_orders.MIN_SEGMENTS` segments the orders' intervals are null with
the reason in ``no_interval``: in the result, the record that carries it and the report. The key
is written only then, so documents without it (every one before) read as before. An interval row
of ``LIMITS`` that meets a null interval judges it unbounded: a ``max_ci_*`` limit fails.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

from eol_cal.analysis.fit.mech_orders import MIN_SEGMENTS
from eol_cal.analysis.motor_result import MotorResult

_FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def _one_load() -> dict:
    """The typed golden of two segments (one load point at two speeds), as ``eol-cal fit`` wrote it."""
    return json.loads((_FIXTURES / "fit_typed" / "one_load.json").read_text())["motors"][0]


def test_two_segments_give_the_orders_no_interval_and_the_reason():
    doc = _one_load()
    res = MotorResult.from_json(doc, "one_load.json")
    assert res.mech is not None and len(res.mech.orders) == 3 and MIN_SEGMENTS == 3
    for o in res.mech.orders:
        assert o.c.ci95 is None and o.phase_c.ci95 is None
        assert o.no_interval is not None and "2 segments" in o.no_interval and "at least 3" in o.no_interval
        assert math.isfinite(o.c.value)  # the estimate stays: only its interval is withheld
    assert res.to_json() == doc  # the reason round-trips


def test_a_result_without_the_key_reads_as_before():
    doc = _one_load()
    old = copy.deepcopy(doc)
    for o in old["mech"]["orders"]:
        del o["no_interval"]
        o["c"]["ci95"], o["phase_c"]["ci95"] = 54.5, math.pi  # what a two-segment fit reported before
    res = MotorResult.from_json(old, "old.json")
    assert res.mech is not None and all(o.no_interval is None for o in res.mech.orders)
    assert res.mech.orders[0].c.ci95 == 54.5
    assert res.to_json() == old  # and is written back without it


def test_a_reason_that_is_not_a_string_is_refused_with_the_field():
    import pytest

    from eol_cal.errors import ResultFormatError

    doc = _one_load()
    doc["mech"]["orders"][1]["no_interval"] = 3
    with pytest.raises(ResultFormatError, match=r"orders\[1\]\.no_interval"):
        MotorResult.from_json(doc, "bad.json")


def test_the_record_and_the_report_carry_the_reason():
    from eol_cal.records.record import RunRecord
    from eol_cal.report.motor_page import mech_section

    doc = json.loads((_FIXTURES / "run_record_demo.json").read_text())
    why = "no interval: 2 segments in identified windows, the segments' scatter needs at least 3"
    for o in doc["fit"]["mech"]["orders"]:
        o["c"]["ci95"] = o["phase_c"]["ci95"] = None
        o["no_interval"] = why
    rec = RunRecord.from_json(doc, "run_record_demo.json")
    assert rec.to_json()["fit"]["mech"]["orders"][0]["no_interval"] == why
    rows = mech_section(rec)["rows"]
    assert all(why in row[1] and "±" not in row[1] for row in rows)


def test_limits_judge_a_missing_interval_as_unbounded():
    """``one_load`` has no phase interval for k6 (c6 left out on one load point): the row
    ``max_ci_phase_k6_deg`` fails it at any value, where the k6 row judges its finite interval."""
    from eol_cal.records.limits import Measured, VariantLimits, judge

    res = MotorResult.from_json(_one_load(), "one_load.json")
    m = Measured.of_fit(res)
    assert m.ci_phase_k6_deg == math.inf
    wide = dict(max_k6=1.0, min_r2=-1.0, max_rms_nm=100.0, max_hall_deviation_deg=180.0, max_ci_c6_nm=100.0,
                max_bench_assumed=1.0, max_pp_before_pct=1000.0, max_pp_after_pct=1000.0, min_improvement_pct=-1000.0)
    lim = VariantLimits.of("v", **wide, max_ci_k6_rel=10.0, max_ci_phase_k6_deg=180.0)
    checks = {c.key: c for c in judge(m, lim, "fit")}
    assert checks["max_ci_phase_k6_deg"].passed is False
    assert checks["max_ci_k6_rel"].passed is True
