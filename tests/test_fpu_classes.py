"""The golden vectors' tolerance classes are measured on the twin, not guessed: the identification
run with the C28x's division and square root (:mod:`eol_cal.firmware.fpu_c28x`) against the
correctly rounded reference, every scenario, tick by tick."""

from __future__ import annotations

import numpy as np
import pytest

from eol_cal.firmware import fpu_c28x as F
from eol_cal.firmware import mech_golden as MG
from eol_cal.firmware.mech_run import run_mech


def test_the_model_is_an_approximation_within_a_few_ulp():
    rng = np.random.default_rng(3)
    a = rng.uniform(-10, 10, 100_000).astype(np.float32)
    b = rng.uniform(1e-3, 1e3, 100_000).astype(np.float32)
    d = F.ulp_distance(F.div(a, b), a / b)
    s = F.ulp_distance(F.sqrt(b), np.sqrt(b))
    assert 0 < d.max() <= 4 and 0 < s.max() <= 4  # not correctly rounded, but close
    assert (d > 0).mean() > 0.05
    assert F.sqrt(np.float32(0.0)) == 0.0


@pytest.mark.slow
def test_the_scenarios_ulp_classes_are_the_twins_measured_bound():
    """The largest difference over every scenario equals the stated class; the decisions (active,
    offset, events) and every other column are identical, so they stay exact."""
    worst = dict.fromkeys(MG.SCENARIO_ULP, 0)
    for sc in MG.SCENARIOS.values():
        a, b, h = sc.signals()
        blk = MG.golden_block(sc.block_id)
        ieee = run_mech(blk, a, b, h, MG.I_QO, standstill_s=sc.standstill_s)
        c28x = run_mech(blk, a, b, h, MG.I_QO, standstill_s=sc.standstill_s, fpu="c28x")
        for col in ieee._fields:
            x, y = getattr(ieee, col), getattr(c28x, col)
            if col in worst:
                worst[col] = max(worst[col], int(F.ulp_distance(x, y).max()))
            else:
                assert np.array_equal(x, y), (sc.block_id, col)
    assert worst == MG.SCENARIO_ULP
