"""The identifier's tick-by-tick reference (:func:`eol_cal.firmware.mech_run.run_mech`, the golden
vectors) ticks on numpy scalars (``SCALAR_NP``) for speed: it must compute exactly what the same
steps compute with ``xp=numpy`` on 0-d arrays, bit for bit, through an identification."""

from __future__ import annotations

import numpy as np
import pytest

from eol_cal.firmware import compensator, estimator as est
from eol_cal.firmware import mech_golden as G
from eol_cal.firmware.block import FLAG_COMP_ENABLE
from eol_cal.firmware.estimator_step import step_pitch
from eol_cal.firmware.mech import EV_EVAL, EV_IDENTIFIED, MechConsts, block_mech_tables, mech_init, mech_sum
from eol_cal.firmware.mech_run import run_mech
from eol_cal.firmware.mech_tick import mech_step


def _numpy_steps(block, a, b, h, i_qo):
    """The three steps of one ECU with ``xp=numpy`` (0-d arrays), tick by tick."""
    cfg = est.EstimatorConfig.from_block(block, standstill_s=1.0)
    mc = MechConsts.of(cfg)
    tb = block_mech_tables(block)
    es = est.init_state(cfg, h[0], a[0], b[0])
    ms = mech_init(mc.N)
    iq = np.float32(i_qo)
    out = {k: [] for k in ("theta_hat", "omega_hat", "status", "learn", "active", "r", "events", "score", "margin",
                           "i_qc")}
    for i in range(len(a)):
        es, eo, ps = step_pitch(cfg, es, a[i], b[i], h[i], xp=np)
        ms, mo = mech_step(mc, tb, ms, es, eo, ps, xp=np)
        sm = mech_sum(mc, tb, mo.r, es.q, eo.theta_hat, eo.omega_hat, iq, xp=np)
        iqc = compensator.i_qc(eo.theta_hat, eo.omega_hat, iq, block.table_const, block.table_per_amp,
                               np.float32(block.lead_s), np.float32(block.iqc_limit), xp=np,
                               mech_on=mo.active != 0, mech_sum=sm)
        for k, v in (("theta_hat", eo.theta_hat), ("omega_hat", eo.omega_hat), ("status", eo.status),
                     ("learn", ps.learn), ("active", mo.active), ("r", mo.r), ("events", mo.events),
                     ("score", mo.score), ("margin", mo.margin), ("i_qc", iqc)):
            out[k].append(v)
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.mark.slow  # 14 000 ticks twice, the 0-d array path ~3 s
def test_the_scalar_reference_is_the_numpy_steps_bit_for_bit():
    sc = G.SCENARIOS["mech_pole_pair_0.csv"]
    block = G.golden_block(sc.block_id)
    assert block.flags & FLAG_COMP_ENABLE
    a, b, h = sc.signals()
    fast = run_mech(block, a, b, h, G.I_QO)
    ref = _numpy_steps(block, a, b, h, G.I_QO)
    assert np.any(fast.events & EV_EVAL) and np.any(fast.events & EV_IDENTIFIED)  # the evaluation ran, identified
    assert np.count_nonzero(fast.i_qc) > len(a) // 4
    for name in ref:
        got = getattr(fast, name)
        want = ref[name].astype(got.dtype)
        assert got.view(np.uint32 if got.dtype == np.float32 else np.int32).tolist() == \
            want.view(np.uint32 if want.dtype == np.float32 else np.int32).tolist(), name
