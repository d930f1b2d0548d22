"""The firmware's estimator, identifier and compensator run together over sampled signals.

:func:`run_mech` is the bit-exact numpy reference of one ECU tick by tick (the golden vectors of
``firmware_params/MECH.md``); :func:`ecu_tick` is one tick of the same three steps written with
``xp`` operations, which the plant's ECU and :mod:`eol_cal.firmware.mech_sim` trace under JAX.
"""

from __future__ import annotations

from typing import NamedTuple, cast

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.firmware import compensator, estimator as est
from eol_cal.firmware.block import FLAG_COMP_ENABLE, ParamBlock
from eol_cal.firmware.estimator_step import EstimatorOut, EstimatorState, PitchSample, step_pitch
from eol_cal.firmware.scalar_numpy import SCALAR_NP, scalar_of
from eol_cal.firmware.mech import (
    MechConsts, MechOut, MechState, MechTables, block_mech_tables, mech_init, mech_sum,
)
from eol_cal.firmware.mech_tick import mech_step


class MechRun(NamedTuple):
    """Per tick of :func:`run_mech` (numpy arrays): the estimator's outputs, its pitch sample's
    ``learn`` flag, the identifier's outputs and the compensating current ``i_qc`` (A)."""

    theta_hat: np.ndarray
    omega_hat: np.ndarray
    status: np.ndarray
    learn: np.ndarray
    active: np.ndarray
    r: np.ndarray
    events: np.ndarray
    score: np.ndarray
    margin: np.ndarray
    i_qc: np.ndarray


def ecu_tick(cfg: est.EstimatorConfig, mc: MechConsts, tb: MechTables, block_tables: tuple[Array, Array, Array, Array],
             es: EstimatorState, ms: MechState, a: Array, b: Array, h: Array, i_qo: Array, comp_on: bool,
             xp: ArrayModule = np, hall_tables: est.HallTables | None = None
             ) -> tuple[EstimatorState, MechState, EstimatorOut, PitchSample, MechOut, Array]:
    """One tick: estimator (with its pitch sample), identifier, compensator (MECH.md, "Per tick").

    ``block_tables`` is ``(table_const, table_per_amp, lead_s, iqc_limit)``; ``comp_on`` (static)
    is the block's ``COMP_ENABLE``. Returns ``(es, ms, EstimatorOut, PitchSample, MechOut, i_qc)``.
    With ``xp=numpy`` the state and inputs are one motor's scalars (:func:`run_mech`).
    """
    xp = scalar_of(xp)
    es, eo, ps = step_pitch(cfg, es, a, b, h, xp=xp, tables=hall_tables)
    ms, mo = mech_step(mc, tb, ms, es, eo, ps, xp=xp)
    if comp_on and xp is SCALAR_NP and mo.active == 0:
        # one motor, nothing identified: i_qc's select would drop the mechanical sum, so it is not
        # computed (the tick-by-tick reference spends a fifth of its time on it)
        tc, tp, lead, limit = block_tables
        iqc = compensator.i_qc(eo.theta_hat, eo.omega_hat, i_qo, tc, tp, lead, limit, xp=xp)
    elif comp_on:
        tc, tp, lead, limit = block_tables
        sm = mech_sum(mc, tb, mo.r, es.q, eo.theta_hat, eo.omega_hat, i_qo, xp=xp)
        iqc = compensator.i_qc(eo.theta_hat, eo.omega_hat, i_qo, tc, tp, lead, limit, xp=xp,
                               mech_on=mo.active != 0, mech_sum=sm)
    else:
        iqc = xp.zeros_like(eo.theta_hat)
    return es, ms, eo, ps, mo, iqc


def _scalars(state):
    return type(state)(*(x[()] if np.ndim(x) == 0 else x for x in state))


def run_mech(block: ParamBlock, enc_a: Array, enc_b: Array, hall: Array, i_qo: Array = 0.0,
             standstill_s: float = 1.0, fpu: str = "ieee") -> MechRun:
    """Run the ECU a block configures over sampled signals (numpy, tick by tick, bit-exact).

    Parameters
    ----------
    block : ParamBlock
        Its estimator options, hall table, tables and (layout 2) mechanical part.
    enc_a, enc_b, hall : int arrays (n,)
        Encoder levels (0/1) and hall states (0..7) per tick; the first sample is also the power-on one.
    i_qo : float or array (n,)
        Nominal q current per tick (A).
    standstill_s : float
        The estimator's standstill bound (s).
    """
    cfg = est.EstimatorConfig.from_block(block, standstill_s=standstill_s)
    mc = MechConsts.of(cfg, fpu)
    tb = block_mech_tables(block)
    a = np.asarray(enc_a, np.int32)
    b = np.asarray(enc_b, np.int32)
    h = np.asarray(hall, np.int32)
    n = len(a)
    iq = np.broadcast_to(np.asarray(i_qo, np.float32), (n,))
    out = {name: np.zeros(n, np.float32 if name in ("theta_hat", "omega_hat", "score", "margin", "i_qc") else np.int32)
           for name in MechRun._fields}
    if n == 0:
        return MechRun(**out)
    es = _scalars(est.init_state(cfg, h[0], a[0], b[0]))
    ms = _scalars(mech_init(mc.N))
    # binary32 scalars, as the ECU holds them (a numpy scalar is none of Array's members to mypy)
    bt = (block.table_const, block.table_per_amp, cast(Array, np.float32(block.lead_s)),
          cast(Array, np.float32(block.iqc_limit)))
    comp_on = bool(block.flags & FLAG_COMP_ENABLE)
    for i in range(n):
        es, ms, eo, ps, mo, iqc = ecu_tick(cfg, mc, tb, bt, es, ms, a[i], b[i], h[i], iq[i], comp_on)
        out["theta_hat"][i], out["omega_hat"][i], out["status"][i] = eo.theta_hat, eo.omega_hat, eo.status
        out["learn"][i] = ps.learn
        out["active"][i], out["r"][i], out["events"][i] = mo.active, mo.r, mo.events
        out["score"][i], out["margin"][i], out["i_qc"][i] = mo.score, mo.margin, iqc
    return MechRun(**out)


__all__ = ["MechRun", "ecu_tick", "run_mech", "MechOut"]
