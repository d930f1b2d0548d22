"""The cycle budget per tick (firmware contract, "Cycle budget"): the C reference's operations
counted on every tick of every golden scenario (an instrumented clang build), weighed with the
F28335 cost model of bench/bench_fw_cycles.py; the worst modelled tick must stay within the
contract's budget, which the evaluation run inside the tick (the structure before) exceeds."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("bench_fw_cycles", ROOT / "bench" / "bench_fw_cycles.py")
C = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(C)

pytestmark = pytest.mark.slow  # builds the instrumented reference and runs every golden file


def test_the_worst_modelled_tick_is_within_the_budget():
    r = C.worst_ticks()
    assert r["harness_rc"] == 0  # the counting build still matches every golden file
    assert len(r["files"]) >= 20
    tick, name, row = r["worst"]["tick"]
    assert 0 < tick <= C.BUDGET, f"worst tick {tick:.0f} cycles ({name} row {row}) over {C.BUDGET:.0f}"
    assert r["worst"]["mech_tick"][0] < 0.1 * C.TICK_CYCLES  # the identifier's part is small and constant


def test_the_evaluation_inside_the_tick_exceeds_the_budget():
    """The check can fail: the same code with every slice of an evaluation run inside the tick."""
    r = C.worst_ticks(eval_in_tick=True)
    assert r["worst"]["tick"][0] > C.BUDGET
    assert r["worst"]["mech_tick"][0] > C.BUDGET


def test_every_cost_has_its_source():
    assert all(cycles > 0 and len(src) > 20 for cycles, src in C.COST.values())
