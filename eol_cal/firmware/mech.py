"""The rotor's mechanical angle without an index pulse, and the mechanical-order compensation
(contract revision 1.2, ``firmware_params/MECH.md``): the reference the C port
(``firmware_params/c/eol_mech.c``), the golden vectors, the plant's ECU and the analysis share.

The 64 PPR encoder has no index and the halls repeat every electrical revolution, so after power-up
the firmware knows the electrical angle but not which of the P/2 pole pairs the rotor is under,
nor which encoder pulse is which. A layout-2 block carries what identifies them:

* the encoder's *fingerprint*: the placement error of each A edge, measured at end of line in the
  block's frame (pulse 0 of that frame is an arbitrary pulse; ``grid_phase`` says where the frame's
  quadrature boundary 0 sits against the halls);
* thresholds: the least cosine of the best hypothesis, the least margin over the next one, the
  largest hall-to-encoder fraction error.

Per tick (:func:`mech_step`, after the estimator's :func:`eol_cal.firmware.estimator.step_pitch`)
the identifier accumulates the pitch sizes the estimator measures at steady speed (improvement 4),
per edge and direction. Once a revolution's worth of new samples is in and every edge of the
current direction has one, it *evaluates*: the halls give the firmware's encoder frame against the
block's up to the pole pair (``P/2`` hypotheses of the pulse offset ``r``, one per pole pair); the
measured pitch errors are correlated (cosine) with the block's pitch errors under each hypothesis;
the best must reach ``id_min_score``, lead the next by ``id_margin`` and agree with the halls within
``id_frac_tol``. Two evaluations in a row that pass with the same ``r`` identify the frame; from then
on every evaluation must give the same ``r`` and the hall fraction is checked at every revolution
mark, else the compensation is withdrawn and the identification starts again. A count or hall
fault (QEP error, a corrected lost pulse, a hall reading 0/7 or out of sequence) withdraws it at
once. Identified, :func:`mech_sum` reads the block's mechanical tables at the rotor's mechanical
angle in the block's frame, and :func:`eol_cal.firmware.compensator.i_qc` adds it before the clamp.

Everything is binary32 in a fixed order with ``xp`` operations only (no Python branch on values):
bit-exact under numpy on one motor (sums run element by element, ``np.add.accumulate``), traced
under ``jax.numpy`` (``vmap`` over motors) for the plant, where XLA's sums and fused multiply-adds
make it float32-close rather than bit-exact.
"""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="arg-type,union-attr,index,operator,return-value"

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.firmware import fpu_c28x
from eol_cal.firmware.compensator import lead_angle, table_sum
from eol_cal.firmware.contract import FLAG_MECH_COMP_ENABLE, FLAGS_MECH_NEEDS
from eol_cal.firmware.estimator_config import (
    F32, I32, PI, ST_HALL_FAULT, ST_HALL_SEQ, ST_MISSING_EDGE, ST_QEP_ERROR, TWO_PI, EstimatorConfig, consts,
    wrap, wrap_pm,
)

from eol_cal.firmware.mech_params import MECH_TABLE_LEN, MechParams

if TYPE_CHECKING:
    from eol_cal.firmware.block import ParamBlock

#: a pitch sample is accumulated only while its edge has fewer (the mean no longer moves; the
#: binary32 sum keeps its resolution)
CNT_MAX = 1024
#: most pole pairs (hypotheses) the identifier evaluates (the C port's EOL_MECH_MAX_PP)
MAX_PP = 64
#: edges whose mean pitch error one background slice computes
SLICE_EDGES = 16
#: estimator status bits after which the count or the halls cannot be trusted: withdraw and start again
RESET_STATUS = ST_QEP_ERROR | ST_MISSING_EDGE | ST_HALL_FAULT | ST_HALL_SEQ

# event bits of MechOut.events
EV_EVAL = 1 << 0
"""An evaluation ran this tick."""
EV_PASS = 1 << 1
"""The evaluation's best hypothesis passed the three thresholds."""
EV_IDENTIFIED = 1 << 2
"""This tick's evaluation confirmed the candidate: the compensation starts."""
EV_RESET_FAULT = 1 << 3
"""A count or hall fault (``RESET_STATUS``) reset the identification."""
EV_RESET_FRACTION = 1 << 4
"""Identified, the hall-to-encoder fraction at a revolution mark disagreed: withdrawn."""
EV_RESET_EVAL = 1 << 5
"""Identified, an evaluation failed or gave another offset: withdrawn."""
EVENT_BITS = {"EVAL": EV_EVAL, "PASS": EV_PASS, "IDENTIFIED": EV_IDENTIFIED, "RESET_FAULT": EV_RESET_FAULT,
              "RESET_FRACTION": EV_RESET_FRACTION, "RESET_EVAL": EV_RESET_EVAL}


@dataclass(frozen=True)
class MechConsts:
    """Static integers and binary32 constants of the identifier (from the estimator's configuration).

    N : pulses per revolution; PP : pole pairs (hypotheses); M : quadrature counts per revolution;
    DELTA, QUARTER : rad electrical of a pitch and a count; INV_DELTA = 1/DELTA; KM : mechanical
    table entries per rad of unwrapped electrical angle, ``MECH_TABLE_LEN / (P * pi)``.
    fpu : "ieee" (division and square root correctly rounded: the golden vectors) or "c28x" (as the
    F28335 computes them, :mod:`eol_cal.firmware.fpu_c28x`: what the vectors' ulp classes measure).
    """

    N: int
    PP: int
    M: int
    DELTA: np.float32
    QUARTER: np.float32
    INV_DELTA: np.float32
    KM: np.float32
    fpu: str = "ieee"

    @classmethod
    def of(cls, cfg: EstimatorConfig, fpu: str = "ieee") -> MechConsts:
        c = consts(cfg)
        # power-on constants are correctly rounded on every target (MECH.md, "Init"): the model
        # covers the divisions of every tick only
        return cls(N=cfg.N_enc, PP=cfg.poles // 2, M=c.M, DELTA=c.DELTA, QUARTER=c.QUARTER,
                   INV_DELTA=F32(1.0) / c.DELTA, KM=F32(MECH_TABLE_LEN) / (F32(cfg.poles) * PI), fpu=fpu)


def _divider(fpu: str, xp: ArrayModule) -> Callable[[Array, Array], Array]:
    """The binary32 division of an FPU model (the C28x's only under numpy)."""
    if fpu == "c28x":
        if xp is not np:
            raise ValueError("the C28x division model runs under numpy only")
        return fpu_c28x.div
    return lambda a, b: a / b


def _sqrt_of(fpu: str, xp: ArrayModule) -> Callable[[Array], Array]:
    """The binary32 square root of an FPU model."""
    return fpu_c28x.sqrt if fpu == "c28x" else xp.sqrt


class MechTables(NamedTuple):
    """What the identifier reads from the block, derived once at init (arrays may be traced).

    enabled : int32 0/1, MECH_COMP_ENABLE honoured (flags, layout 2, a fingerprint).
    dirs : int32, fp_dirs.
    dF : f32[2N] the fingerprint's pitch errors, ``fp[2m+d] - fp[2((m-1) mod N)+d]`` (rad).
    EF : f32[2] their energy per direction, ``sum_m dF[2m+d]**2`` (element by element).
    grid_phase, id_min_score, id_margin, id_frac_tol, lead_s : f32 (rad, 1, 1, rad, s).
    table_const, table_per_amp : f32[MECH_TABLE_LEN] (A, A/A).
    """

    enabled: Array
    dirs: Array
    dF: Array
    EF: Array
    grid_phase: Array
    id_min_score: Array
    id_margin: Array
    id_frac_tol: Array
    lead_s: Array
    table_const: Array
    table_per_amp: Array


class MechState(NamedTuple):
    """The identifier's state (all zero at power-on but ``cand`` = -1 and ``miss`` = N).

    acc : f32[2N] sum of the pitch samples per edge and direction (index ``2m + d``, d = 1 reverse).
    cnt : i32[2N] samples in ``acc``, saturating at CNT_MAX.
    n_new : i32 samples since the last evaluation started (saturating at N).
    cand : i32 offset that passed the last evaluation (-1: none).
    active : i32 0/1 identified: the mechanical compensation runs.
    r : i32 the identified offset: firmware pulse m is the block's pulse (m + r) mod N.
    score, margin : f32 the last evaluation's best cosine and its margin over the next.
    miss : i32[2] edges of each direction without a sample yet.
    busy : i32 the background evaluation: 0 none, k = its k-th slice is next (1..L), L+1 finished.
    ev_d, ev_G : i32, f32 its direction and the grid offset G when it started.
    ev_ok, ev_r, ev_score, ev_margin : its result (valid once finished).
    mk : i32 the revolution mark's check: 0 none, 1 asked (at a mark), 2 done.
    mk_d, mk_G, mk_bad : i32, f32, i32 its direction, G at the mark, and its verdict.
    clr : i32 after a withdrawal, the background's clearing of the samples: 0 done, k its slice k next.
    """

    acc: Array
    cnt: Array
    n_new: Array
    cand: Array
    active: Array
    r: Array
    score: Array
    margin: Array
    miss: Array
    busy: Array
    ev_d: Array
    ev_G: Array
    ev_ok: Array
    ev_r: Array
    ev_score: Array
    ev_margin: Array
    mk: Array
    mk_d: Array
    mk_G: Array
    mk_bad: Array
    clr: Array


class MechOut(NamedTuple):
    """Per tick: ``active`` (0/1), ``r``, ``events`` (EV_* bits), ``score`` and ``margin`` of the last evaluation."""

    active: Array
    r: Array
    events: Array
    score: Array
    margin: Array


def _seq_sum(x: Array, xp: ArrayModule) -> Array:
    """Sum of the last axis, element by element in binary32 under numpy (the C loop's order)."""
    if xp is np:
        return np.add.accumulate(np.asarray(x, np.float32), axis=-1)[..., -1]
    return xp.sum(x, axis=-1)


def mech_enabled(flags: int, layout_version: int, mech: MechParams | None) -> bool:
    """Whether a block's mechanical compensation is honoured: layout 2, ``MECH_COMP_ENABLE`` with
    ``COMP_ENABLE``, ``INTERP_ENABLE`` and ``EST_LEARN_PITCH_ERRORS``, and a measured fingerprint."""
    return (layout_version >= 2 and mech is not None and bool(flags & FLAG_MECH_COMP_ENABLE)
            and flags & FLAGS_MECH_NEEDS == FLAGS_MECH_NEEDS and mech.fp_dirs != 0)


def mech_tables(mech: MechParams | None, lead_s: float, enabled: bool, N: int) -> MechTables:
    """The identifier's tables of a block's mechanical part (numpy binary32; MECH.md "Init").

    A block without one (layout 1) gives disabled, all-zero tables of the right shapes.
    """
    f32 = np.float32
    if mech is None or mech.fingerprint.size != 2 * N:
        fp = np.zeros(2 * N, f32)
        tc = tp = np.zeros(MECH_TABLE_LEN, f32)
        scal: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
        dirs, enabled = 0, False
    else:
        fp = np.asarray(mech.fingerprint, f32)
        tc, tp = mech.mech_table_const, mech.mech_table_per_amp
        scal = (mech.grid_phase, mech.id_min_score, mech.id_margin, mech.id_frac_tol)
        dirs = mech.fp_dirs
    prev = np.roll(fp.reshape(N, 2), 1, axis=0).reshape(-1)
    dF = (fp - prev).astype(f32)
    EF = np.array([_seq_sum(dF[d::2] * dF[d::2], np) for d in (0, 1)], f32)
    gp, lo, margin, frac = (f32(v) for v in scal)
    return MechTables(enabled=I32(int(enabled)), dirs=I32(dirs), dF=dF, EF=EF, grid_phase=gp, id_min_score=lo,
                      id_margin=margin, id_frac_tol=frac, lead_s=f32(lead_s),
                      table_const=np.asarray(tc, f32), table_per_amp=np.asarray(tp, f32))


def block_mech_tables(block: ParamBlock, N: int | None = None) -> MechTables:
    """:func:`mech_tables` of a :class:`eol_cal.firmware.block.ParamBlock` (layout 1: disabled)."""
    N = int(block.encoder_ppr) if N is None else N
    mech = getattr(block, "mech", None)
    enabled = mech_enabled(block.flags, block.layout_version, mech) and int(block.poles) // 2 <= MAX_PP
    return mech_tables(mech, block.lead_s, enabled, N)


def mech_init(N: int, xp: ArrayModule = np) -> MechState:
    """Power-on state of the identifier for an encoder of ``N`` pulses."""
    zi = xp.asarray(I32(0))
    zf = xp.asarray(F32(0.0))
    return MechState(acc=xp.zeros(2 * N, xp.float32), cnt=xp.zeros(2 * N, xp.int32), n_new=zi,
                     cand=xp.asarray(I32(-1)), active=zi, r=zi, score=zf, margin=zf,
                     miss=xp.full(2, N, dtype=xp.int32), busy=zi, ev_d=zi, ev_G=zf, ev_ok=zi, ev_r=zi, ev_score=zf,
                     ev_margin=zf, mk=zi, mk_d=zi, mk_G=zf, mk_bad=zi, clr=zi)


def n_slices(mc: MechConsts) -> int:
    """Background slices of one evaluation (MECH.md, "Background"): the grid (1), the mean pitch
    errors 16 edges a slice, the norm (1), one per hypothesis, the verdict (1)."""
    return 1 + -(-mc.N // SLICE_EDGES) + 1 + mc.PP + 1


def set_add(arr: Array, idx: Array, val: Array, xp: ArrayModule, scatter: bool = False) -> Array:
    """``arr`` with ``arr[idx] += val`` (a copy under numpy, a functional update under JAX).

    Under JAX a select against the position (``idx`` in range: the same sum at ``idx``, the same
    array bit for bit): ``.at[idx].add`` becomes a scatter once the tick is vmapped over motors,
    and a scatter keeps XLA's CPU backend from compiling the plant's tick loop into one kernel
    (:mod:`eol_cal.numerics.xla`): layout 2's batch ran ~1.5x slower per tick for it.
    ``scatter``: ``.at[idx].add`` all the same, for a scan that is a sequence of XLA's operations
    anyway (the power-ups', :mod:`eol_cal.firmware.mech_sim`: the select rewrote every entry of
    every member's tables on each tick some member took a sample)."""
    if hasattr(arr, "at"):
        if scatter:
            return arr.at[idx].add(val)
        return xp.where(xp.arange(arr.shape[-1], dtype=xp.int32) == idx, arr + val, arr)
    out = arr.copy()
    out[idx] = out[idx] + val
    return out


def mean_c_of(mc: MechConsts, c_tab: Array, d: Array, xp: ArrayModule) -> Array:
    """The mean of the estimator's learned edge errors of direction ``d`` (rad)."""
    idx = I32(2) * xp.arange(mc.N, dtype=xp.int32) + d
    return _divider(mc.fpu, xp)(_seq_sum(xp.take(c_tab, idx), xp), F32(mc.N))


def evaluate(mc: MechConsts, tb: MechTables, ms: MechState, c_tab: Array, G: Array, d: Array,
              xp: ArrayModule) -> tuple[Array, Array, Array, Array]:
    """One evaluation (MECH.md, "Evaluation") on the frozen samples, the grid offset ``G`` when it
    started and the estimator's ``c_tab`` now: (pass, r_best, score, margin)."""
    f32, i32 = xp.float32, xp.int32
    N = mc.N
    m = xp.arange(N, dtype=xp.int32)
    idx = I32(2) * m + d
    cnt_d = xp.take(ms.cnt, idx)
    div = _divider(mc.fpu, xp)
    dg = wrap((G + mean_c_of(mc, c_tab, d, xp)) - tb.grid_phase, xp)
    a = div(xp.take(ms.acc, idx), f32(xp.maximum(cnt_d, I32(1))))
    Ea = _seq_sum(a * a, xp)
    EF = xp.take(tb.EF, d)
    den = _sqrt_of(mc.fpu, xp)(Ea * EF)
    best_rho = best_r = best_e = None
    rhos, rs = [], []
    for j in range(mc.PP):
        x = (dg + TWO_PI * F32(j)) * mc.INV_DELTA
        r = xp.floor(x + F32(0.5)).astype(i32) % I32(N)
        e = wrap_pm(dg - f32(r) * mc.DELTA, xp)
        s = _seq_sum(a * xp.take(tb.dF, I32(2) * ((m + r) % I32(N)) + d), xp)
        rho = xp.where(den > F32(0.0), div(s, xp.where(den > F32(0.0), den, F32(1.0))), F32(0.0))
        if j == 0:
            best_rho, best_r, best_e, best_j = rho, r, e, xp.asarray(I32(0))
        else:
            better = rho > best_rho
            best_rho = xp.where(better, rho, best_rho)
            best_r = xp.where(better, r, best_r)
            best_e = xp.where(better, e, best_e)
            best_j = xp.where(better, I32(j), best_j)
        rhos.append(rho)
        rs.append(r)
    second = xp.asarray(F32(0.0))
    for j, rho in enumerate(rhos):
        second = xp.where(best_j != I32(j), xp.maximum(second, rho), second)
    margin = best_rho - second
    ok = (best_rho >= tb.id_min_score) & (margin >= tb.id_margin) & (xp.abs(best_e) <= tb.id_frac_tol)
    return ok, best_r, best_rho, margin


def f32_(x: Array, xp: ArrayModule) -> Array:
    """``(float)x`` of an int32 (a named step so the order of operations reads as in MECH.md)."""
    return xp.asarray(x).astype(xp.float32)


def mech_sum(mc: MechConsts, tb: MechTables, r: Array, q: Array, theta_hat: Array, omega_hat: Array,
             i_qo: Array, xp: ArrayModule = np) -> Array:
    """The mechanical-order current before the clamp (A, MECH.md "Compensation").

    The rotor's count ``q`` in the block's frame is ``k = (q + 4r) mod M``; its boundary sits at
    the unwrapped electrical angle ``E_k = grid_phase + k*QUARTER`` (in [0, 8*pi)); the lead angle
    ``t`` is placed beside it, ``E = E_k + wrap_pm(t - E_k)``, and the mechanical tables are read at
    ``E * KM`` (KM = table entries per rad electrical: the mechanical angle is ``E / (P/2)``).
    """
    t = lead_angle(theta_hat, omega_hat, tb.lead_s, xp)
    k = (xp.asarray(q, dtype=xp.int32) + I32(4) * xp.asarray(r, dtype=xp.int32)) % I32(mc.M)
    Ek = tb.grid_phase + f32_(k, xp) * mc.QUARTER
    E = Ek + wrap_pm(t - Ek, xp)
    return table_sum(E, i_qo, tb.table_const, tb.table_per_amp, mc.KM, xp)


def block_frame_angle(mc: MechConsts, grid_phase: float, r: Array, q: Array, theta: Array, xp: ArrayModule = np) -> Array:
    """The rotor's mechanical angle in the block's frame (rad, [0, 2*pi)) from the count ``q``, the
    offset ``r`` and the electrical angle ``theta`` (rad): what :func:`mech_sum` reads the tables at,
    for plots and the analysis (float64 under numpy)."""
    M = mc.M
    k = (np.asarray(q) + 4 * np.asarray(r)) % M
    Ek = grid_phase + k * float(mc.QUARTER)
    E = Ek + (np.asarray(theta) - Ek + math.pi) % (2 * math.pi) - math.pi
    return np.mod(E / mc.PP, 2 * math.pi)
