"""One tick of the firmware's angle and speed estimator (ESTIMATOR.md, "State" and "Per tick").

:func:`step` is written once with ``xp`` operations only (no Python branch on values), so with
``xp=numpy`` on scalars it is the bit-exact binary32 reference for the C port
(``firmware_params/c/eol_est.c``) and the golden vectors, and with ``xp=jax.numpy`` it traces
inside ``jit``/``vmap``/``lax.scan`` (the plant's ECU). :mod:`eol_cal.firmware.estimator` runs it
over whole captures.
"""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="arg-type,union-attr,index,operator,assignment"

from typing import NamedTuple, cast

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.firmware.scalar_numpy import SCALAR_NP, when
from eol_cal.firmware.estimator_config import (
    F32, HALF, I32, K_ACC, K_PITCH, N_LEARN, ST_DIR_MISMATCH, ST_EDGE_REJECT, ST_HALL_FAULT, ST_HALL_SEQ,
    ST_MISSING_EDGE, ST_NO_ANCHOR, ST_NO_SPEED, ST_QEP_ERROR, ST_REVERSE, ST_STANDSTILL, STEADY_TICKS,
    TICK_MASK, TWO_PI, EstimatorConfig, HallTables, consts, wrap, wrap_pm,
)

class EstimatorState(NamedTuple):
    """Everything the estimator keeps between ticks (int32 / float32, scalars or batched).

    Batched states: any leading shape with ``xp=numpy`` (bit-exact per element) as long as
    ``learn_pitch_errors`` is off; with it on, batch through ``jax.vmap`` (its per-motor tables
    are indexed per motor).

    phase : quadrature phase of (A, B): (0,0)=0, (1,0)=1, (1,1)=2, (0,1)=3.
    q : quadrature count, 0 .. 4*N_enc-1.
    n : ticks since the last A edge event, saturating at standstill_ticks + 1.
    k_last : quadrature boundary index of the last A edge event (its angle is G + k*QUARTER).
    dir_last : direction of the last A edge event (+1, -1; 0 before the first).
    nc_prev : N_c of the last measured interval (ticks; 0 = none).
    against : a quadrature step against dir_last happened since the last edge event (0/1).
    omega : omega_hat from the last measured interval (rad/s electrical, signed).
    alpha : filtered acceleration estimate (rad/s^2 electrical), improvement 3 only.
    adv : angle advanced since the last edge event (rad electrical).
    G : encoder-grid offset: electrical angle of quadrature boundary 0 (rad, [0, 2*pi)).
    hall_last : last valid hall reading (1..6; 0 = none yet).
    sector : last hall state reached through an adjacent transition or at start-up (0 = none).
    anchored : a hall transition has set G (0/1).
    n_anchor : hall corrections since the anchor or the last count slip, saturating at N_LEARN.
    tick : free-running tick counter modulo 2**30 (improvement 4).
    run : measured intervals in a row in one direction, saturating at N_enc (improvement 4).
    R_prev : revolution time at the previous measured edge (ticks; improvement 4).
    c_tab : f32[2*N_enc] learned placement error of each A edge (rad electrical, index k >> 1;
        improvement 4, else empty).
    ts : i32[2*N_enc] tick of each A edge's last event (improvement 4, else empty).
    """

    phase: Array
    q: Array
    n: Array
    k_last: Array
    dir_last: Array
    nc_prev: Array
    against: Array
    omega: Array
    alpha: Array
    adv: Array
    G: Array
    hall_last: Array
    sector: Array
    anchored: Array
    n_anchor: Array
    tick: Array
    run: Array
    R_prev: Array
    c_tab: Array
    ts: Array


class PitchSample(NamedTuple):
    """What improvement 4 measured this tick (the mechanical identifier's input,
    ``firmware_params/MECH.md``); all zero without ``learn_pitch_errors``.

    learn : 1 when this tick's A edge closed a pitch at steady speed (the estimator learnt).
    index : c_tab index (``k >> 1``) of the edge that ENDS the pitch in forward rotation: the new
        edge forward, the previous edge in reverse (so forward and reverse samples of one pitch
        share the parity of their direction and the pulse index ``index >> 1``).
    error : the pitch's size minus ``DELTA`` (rad electrical): ``n1 * (K_NDELTA / R) - DELTA``.
    """

    learn: Array
    index: Array
    error: Array


class EstimatorOut(NamedTuple):
    """Per-tick outputs.

    theta_hat : estimated electrical angle (rad, [0, 2*pi)).
    omega_hat : estimated electrical speed (rad/s, signed; + = forward).
    theta_enc : raw edge-quantised electrical angle, the angle of the last A edge event
        (rad, [0, 2*pi)); the paper's 'raw' encoder angle.
    status : ST_* bits (int32).
    """

    theta_hat: Array
    omega_hat: Array
    theta_enc: Array
    status: Array


class _Edge(NamedTuple):
    """What step 2 (the A edge event) of :func:`step_pitch` hands on."""

    ev: Array
    bounce: Array
    missing: Array
    reject: Array
    speed_upd: Array
    q: Array
    k: Array
    against: Array
    n: Array
    k_last: Array
    dir_last: Array
    omega: Array
    nc_prev: Array
    alpha: Array
    tick: Array
    run: Array
    R_prev: Array
    c_tab: Array
    ts: Array
    sample: PitchSample


def _tab(table: np.ndarray, idx: Array, xp: ArrayModule) -> Array:
    """``table[idx]`` for a constant or traced table and a (possibly traced) int32 index."""
    return table[idx] if xp is np or xp is SCALAR_NP else xp.asarray(table)[idx]


# The step's constants built once (numpy int32/float32 scalars, the same under numpy and JAX).
_I0 = I32(0)
_I1 = I32(1)
_I2 = I32(2)
_I3 = I32(3)
_I4 = I32(4)
_I_ST_STANDSTILL = I32(ST_STANDSTILL)
_I_ST_REVERSE = I32(ST_REVERSE)
_I_ST_HALL_FAULT = I32(ST_HALL_FAULT)
_I_ST_HALL_SEQ = I32(ST_HALL_SEQ)
_I_ST_NO_ANCHOR = I32(ST_NO_ANCHOR)
_I_ST_QEP_ERROR = I32(ST_QEP_ERROR)
_I_ST_EDGE_REJECT = I32(ST_EDGE_REJECT)
_I_ST_MISSING_EDGE = I32(ST_MISSING_EDGE)
_I_ST_DIR_MISMATCH = I32(ST_DIR_MISMATCH)
_I_ST_NO_SPEED = I32(ST_NO_SPEED)
_I_TICK_MASK = I32(TICK_MASK)
_I_N_LEARN = I32(N_LEARN)
_I_STEADY_TICKS = I32(STEADY_TICKS)
_F0, _F1 = F32(0.0), F32(1.0)
_FALSE = cast(Array, np.False_)  # a flag no member raises, typed as the step's arrays


def _set(arr: Array, idx: Array, val: Array, xp: ArrayModule, scatter: bool = False) -> Array:
    """``arr`` with ``arr[idx] = val`` (a copy under numpy, a functional update under JAX).

    Under JAX a select against the position (``idx`` in range: the same array bit for bit):
    ``.at[idx].set`` becomes a scatter once the step is vmapped over motors or captures, which
    XLA's CPU backend runs outside a tick loop compiled into its loop kernel, ~20x slower per
    tick. ``scatter``: ``.at[idx].set`` all the same, for a scan that is a sequence of XLA's
    operations anyway (:func:`step_pitch`'s ``scatter_tables``)."""
    if not hasattr(arr, "at"):
        out = arr.copy()
        out[idx] = val
        return out
    if scatter:
        return arr.at[idx].set(val)
    return xp.where(xp.arange(arr.shape[-1], dtype=xp.int32) == idx, val, arr)


def _dq(q: Array, k_last: Array, M: int, xp: ArrayModule) -> Array:
    """Signed quadrature counts from boundary ``k_last`` to count ``q``, in [-M/2, M/2)."""
    return (q - k_last + I32(M + M // 2)) % I32(M) - I32(M // 2)


def quadrature_phase(enc_a: Array, enc_b: Array) -> Array:
    """Position of the encoder levels (0/1 integers) in one quadrature cycle, forward: 00 -> 10 -> 11 -> 01 is 0, 1, 2, 3."""
    return _I2 * enc_b + (enc_a ^ enc_b)


def init_state(cfg: EstimatorConfig, hall0: Array, enc_a0: Array = 0, enc_b0: Array = 0,
               xp: ArrayModule = np) -> EstimatorState:
    """Power-on state from the first sample of the halls (and the encoder levels).

    Parameters
    ----------
    cfg : EstimatorConfig
    hall0 : int or int array
        Hall state at power-on (0..7; 0 and 7 leave the sector unknown until a valid reading).
    enc_a0, enc_b0 : int or int array
        Encoder levels at power-on (0/1), so the first tick counts no spurious step.
    xp : numpy or jax.numpy
    """
    h = xp.asarray(hall0).astype(xp.int32)
    a = xp.asarray(enc_a0).astype(xp.int32) + xp.zeros_like(h)
    b = xp.asarray(enc_b0).astype(xp.int32) + xp.zeros_like(h)
    valid = (h >= 1) & (h <= 6)
    L = 2 * cfg.N_enc if cfg.learn_pitch_errors else 0
    h = xp.where(valid, h, xp.zeros_like(h))
    zi = xp.zeros_like(h)
    zf = zi.astype(xp.float32)
    ph = quadrature_phase(a, b)
    return EstimatorState(phase=ph, q=ph, n=zi, k_last=zi, dir_last=zi, nc_prev=zi, against=zi,
                          omega=zf, alpha=zf, adv=zf, G=zf, hall_last=h, sector=h, anchored=zi,
                          n_anchor=zi, tick=zi, run=zi, R_prev=zi,
                          c_tab=xp.zeros(h.shape + (L,), xp.float32),
                          ts=xp.zeros(h.shape + (L,), xp.int32))


def step(cfg: EstimatorConfig, state: EstimatorState, enc_a: Array, enc_b: Array, hall: Array,
         xp: ArrayModule = np, tables: HallTables | None = None, batch_axis: str | None = None
         ) -> tuple[EstimatorState, EstimatorOut]:
    """One PWM tick of the estimator (ESTIMATOR.md, "Per tick"): :func:`step_pitch` without its
    pitch sample."""
    new, out, _ = step_pitch(cfg, state, enc_a, enc_b, hall, xp, tables, batch_axis)
    return new, out


def step_pitch(cfg: EstimatorConfig, state: EstimatorState, enc_a: Array, enc_b: Array, hall: Array,
               xp: ArrayModule = np, tables: HallTables | None = None, batch_axis: str | None = None,
               scatter_tables: bool = False) -> tuple[EstimatorState, EstimatorOut, PitchSample]:
    """One PWM tick of the estimator (ESTIMATOR.md, "Per tick"), with what improvement 4 measured.

    Parameters
    ----------
    cfg : EstimatorConfig
        Static; its booleans select code paths at trace time.
    state : EstimatorState
    enc_a, enc_b : int (0/1) or int arrays
        Encoder channel levels sampled this tick.
    hall : int (0..7) or int array
        Hall bits U | V<<1 | W<<2 sampled this tick.
    xp : numpy or jax.numpy
    tables : HallTables, optional
        One motor's hall lookups (f32[8] each, rad; may be traced), used instead of those of
        ``cfg.hall_angle``: a calibrated table is data, not a reason to compile again.
    batch_axis : str, optional
        Under JAX, one member of a batch ``jax.vmap``-ped with this ``axis_name``: the A edge
        event's arithmetic then runs on the ticks some member has an A edge, the hall re-anchor's
        on those some member has an adjacent transition (a branch for the batch; under ``vmap`` a
        branch on a member's value computes both sides), the same result.
    scatter_tables : bool
        Under JAX, an A edge writes its entry of the pitch tables (``c_tab``, ``ts``) by a scatter,
        not by a select over every entry: the same arrays. Cheaper in a batch's scan of XLA's
        operations whose edge branch some member takes on most ticks (the identifier's power-ups,
        :mod:`eol_cal.firmware.mech_sim`: 430 -> 210 ns a power-up a tick, 500 power-ups); dearer in
        a scan compiled into XLA's loop kernel (the plant's, :func:`_set`).

    Returns
    -------
    (new state, EstimatorOut, PitchSample)
    """
    c = consts(cfg)
    ht = HallTables(c.H_START, c.H_WIDTH, c.H_MID) if tables is None else tables
    i32, f32 = xp.int32, xp.float32
    M, S = c.M, c.S
    one = _I1
    Mi, Si, S1i, Ni = I32(M), I32(S), I32(S + 1), I32(cfg.N_enc)
    s = state

    # 1. Quadrature decoding (x4). A rising edge: phase 0->1 forward, 3->2 reverse.
    a = i32(enc_a)
    b = i32(enc_b)
    ph = quadrature_phase(a, b)
    d = (ph - s.phase + _I4) % _I4
    stp = xp.where(d == 1, one, xp.where(d == 3, -one, _I0))
    qep_err = d == 2
    q = (s.q + stp + Mi) % Mi
    a_rise = ((d == 1) & (ph == 1)) | ((d == 3) & (ph == 2))
    edir = xp.where(ph == 1, one, -one)
    k = xp.where(edir > 0, q, (q + one) % Mi)
    against = s.against | i32((stp != 0) & (stp == -s.dir_last))
    n1 = xp.minimum(s.n + one, S1i)

    # 2. A edge event: bounce (same boundary again), measured interval, or re-reference only.
    def no_edge() -> _Edge:
        # No A edge this tick (most ticks): every select of edge() keeps the state; the values
        # those selects give, bit for bit, without computing them.
        if cfg.learn_pitch_errors:
            tick = (s.tick + one) & _I_TICK_MASK
            sample = PitchSample(learn=_I0, index=xp.where(edir > 0, k >> one, s.k_last >> one), error=_F0)
        else:
            tick = s.tick
            sample = PitchSample(learn=_I0 * edir, index=_I0 * edir, error=_F0 * f32(edir))
        return _Edge(_FALSE, _FALSE, _FALSE, _FALSE, _FALSE, q, k, against, n1, s.k_last, s.dir_last, s.omega,
                     s.nc_prev, s.alpha, tick, s.run, s.R_prev, s.c_tab, s.ts, sample)

    def edge() -> _Edge:
        bounce = a_rise & (k == s.k_last) & (edir == s.dir_last)
        ev = a_rise & ~bounce
        same_dir = edir == s.dir_last
        pitch_ok = k == (s.k_last + _I4 * edir + Mi) % Mi
        interval = ev & same_dir & pitch_ok & (n1 <= Si)
        long_iv = interval & (s.nc_prev > 0) & (_I2 * n1 > _I3 * s.nc_prev)
        missing = long_iv & (against != 0)
        reject = long_iv & (against == 0)
        measured = interval & ~long_iv
        nc_eff = xp.where(missing, n1 // _I2, n1)
        omega_new = f32(edir) * (c.K_OMEGA / f32(nc_eff))
        # A lost A pulse leaves the count one pitch behind: put it back.
        fix = xp.where(missing, _I4 * edir, _I0)
        q_fixed = (q + fix + Mi) % Mi
        k_fixed = (k + fix + Mi) % Mi
        speed_upd = measured | missing
        if cfg.learn_pitch_errors:
            tick = (s.tick + one) & _I_TICK_MASK
            i_new = k_fixed >> one
            c_old = s.c_tab[s.k_last >> one]
            c_new = s.c_tab[i_new]
            R = xp.maximum((tick - s.ts[i_new]) & _I_TICK_MASK, one)
            learn = measured & (s.run >= Ni) & (xp.abs(R - s.R_prev) <= _I_STEADY_TICKS)
            # At steady speed the same edge's revolution time gives the true speed, so this pitch's
            # real size is N_enc*DELTA * N_c / R; its edge sits that far from the previous one.
            pitch = f32(n1) * (c.K_NDELTA / f32(R))
            pitch_err = pitch - c.DELTA
            target = c_old + f32(edir) * pitch_err
            c_new = xp.where(learn, c_new + K_PITCH * (target - c_new), c_new)
            c_tab = _set(s.c_tab, i_new, c_new, xp, scatter_tables)
            ts = _set(s.ts, i_new, xp.where(ev, tick, s.ts[i_new]), xp, scatter_tables)
            R_prev = xp.where(measured, R, s.R_prev)
            run = xp.where(measured, xp.minimum(s.run + one, Ni),
                           xp.where(ev, _I0, s.run))
            omega_new = xp.where(measured, f32(edir)
                                 * (((c.DELTA + f32(edir) * (c_new - c_old)) * c.TICK_HZ)
                                    / f32(n1)), omega_new)
            sample = PitchSample(learn=i32(learn), index=xp.where(edir > 0, i_new, s.k_last >> one),
                                 error=xp.where(learn, pitch_err, _F0))
        else:
            tick, run, R_prev, c_tab, ts = s.tick, s.run, s.R_prev, s.c_tab, s.ts
            sample = PitchSample(learn=_I0 * edir, index=_I0 * edir, error=_F0 * f32(edir))
        omega = xp.where(speed_upd, omega_new,
                         xp.where(ev & ~same_dir, _F0, s.omega))
        nc_prev = xp.where(speed_upd, nc_eff,
                           xp.where(reject, n1, xp.where(ev, _I0, s.nc_prev)))
        if cfg.accel_prediction:
            consecutive = measured & (s.nc_prev > 0)
            alpha_raw = (omega_new - s.omega) * (c.TWO_TICK_HZ / f32(n1 + s.nc_prev))
            alpha = xp.where(consecutive, s.alpha + K_ACC * (alpha_raw - s.alpha),
                             xp.where(ev & ~(missing | reject), _F0, s.alpha))
        else:
            alpha = s.alpha
        return _Edge(ev, bounce, missing, reject, speed_upd, q_fixed, k_fixed, xp.where(ev, _I0, against),
                     xp.where(ev, _I0, n1), xp.where(ev, k_fixed, s.k_last), xp.where(ev, edir, s.dir_last), omega,
                     nc_prev, alpha, tick, run, R_prev, c_tab, ts, sample)

    e2 = when(a_rise, edge, no_edge, xp, batch_axis)
    (ev, bounce, missing, reject, speed_upd, q, k, against, n, k_last, dir_last, omega, nc_prev, alpha, tick, run,
     R_prev, c_tab, ts, sample) = e2

    # 3. Standstill and the prediction between edges (eq. 16).
    still = n > Si
    nc_prev = xp.where(still, _I0, nc_prev)
    # omega_hat is valid exactly while nc_prev > 0 (a measured interval since the last break).
    speed_ok = nc_prev > 0
    omega = xp.where(speed_ok, omega, _F0)
    run = xp.where(still, _I0, run)
    alpha = xp.where(still, _F0, alpha)
    if cfg.accel_prediction:
        # omega from an interval is the mean over it: the speed at its middle, N_c/2 ticks back.
        tau = (f32(nc_prev) * HALF + f32(n)) * c.T
        omega_pred = omega + alpha * tau
    else:
        omega_pred = omega
    adv = xp.where(ev, _F0, s.adv + omega_pred * c.T)
    if cfg.clamp_to_next_edge:
        # The rotor is inside the current quadrature count: the prediction never passes its far
        # boundary (so never the next edge) and catches up with its near one. Not after a step
        # against the direction since the last edge: then the count may be a lost pulse behind.
        lo = f32(_dq(q, k_last, M, xp)) * c.QUARTER
        adv = xp.where(against == 0, xp.minimum(xp.maximum(adv, lo), lo + c.QUARTER), adv)

    # 4. Halls: validity, sequence, absolute re-anchor at transitions.
    h = i32(hall)
    hv = (h >= 1) & (h <= 6)
    hl = s.hall_last
    trans = hv & (h != hl) & (hl != 0)
    if xp is SCALAR_NP and not trans:  # one motor, no transition (most ticks): no lookups
        fwd = adj = jump = _FALSE
    else:
        fwd = trans & (h == _tab(c.NEXT, hl, xp))
        rev = trans & (hl == _tab(c.NEXT, xp.where(hv, h, _I0), xp))
        adj = fwd | rev
        jump = trans & ~adj
    first = hv & (hl == 0)
    # First anchor without an edge yet: the grid reference is the current count's middle.
    no_edge = dir_last == 0
    k_last = xp.where(adj & (s.anchored == 0) & no_edge, q, k_last)
    c_last = c_tab[k_last >> one] if cfg.learn_pitch_errors else _F0
    rel = f32(k_last) * c.QUARTER + c_last
    # Without a valid speed the best position is the middle of the current quadrature count.
    cell = f32(_dq(q, k_last, M, xp)) * c.QUARTER + c.HALF_QUARTER
    adv_eff = xp.where(speed_ok, adv, cell)
    def no_anchor() -> tuple[Array, Array, Array, Array]:
        # no adjacent transition: the re-anchor's selects keep G and its counters
        return s.G, s.anchored, s.n_anchor, _FALSE

    def anchor() -> tuple[Array, Array, Array, Array]:
        hb = xp.where(fwd, _tab(ht.start, xp.where(hv, h, _I0), xp), _tab(ht.start, hl, xp))
        theta_pred = wrap(wrap(s.G + rel, xp) + adv_eff, xp)
        e = wrap_pm(hb - theta_pred, xp)
        big = xp.abs(e) > c.HALF_DELTA
        if cfg.learn_grid_offset:
            # Running mean of the corrections over the first N_LEARN transitions, then a first-order
            # filter; an error over half a pitch is a count slip and is taken whole.
            gain = _F1 / f32(xp.minimum(s.n_anchor + one, _I_N_LEARN))
            g = xp.where(big, e, e * gain)
        else:
            g = e
        G = xp.where(adj & (s.anchored != 0), wrap(s.G + g, xp),
                     xp.where(adj, wrap(hb - (rel + adv_eff), xp), s.G))
        anchored = xp.where(adj, one, s.anchored)
        n_anchor = xp.where(adj & ((s.anchored == 0) | big), one,
                            xp.where(adj, xp.minimum(s.n_anchor + one, _I_N_LEARN), s.n_anchor))
        hdir = xp.where(fwd, one, -one)
        return G, anchored, n_anchor, adj & (dir_last != 0) & (hdir != dir_last)

    G, anchored, n_anchor, dir_mismatch = when(adj, anchor, no_anchor, xp, batch_axis)
    hall_last = xp.where(hv, h, hl)
    sector = xp.where(adj | first, h, s.sector)

    # 5. Outputs.
    theta_enc = wrap(G + rel, xp)
    theta = wrap(theta_enc + adv_eff, xp)
    start = _tab(ht.start, sector, xp)
    width = _tab(ht.width, sector, xp)
    dd = wrap(theta - start, xp)
    outside = dd > width
    end = wrap(start + width, xp)
    clamped = xp.where(outside, xp.where(dd - width < TWO_PI - dd, end, start), theta)
    theta = xp.where(still, clamped, theta)
    unanchored = anchored == 0
    mid = _tab(ht.mid, sector, xp)
    theta = xp.where(unanchored, mid, theta)
    theta_enc = xp.where(unanchored, mid, theta_enc)
    omega_out = omega_pred
    if cfg.clamp_to_next_edge:
        # No edge for n ticks: |speed| cannot exceed a pitch per n ticks.
        bound = c.K_OMEGA / f32(xp.maximum(n, one))
        omega_out = xp.where(n > 0, xp.minimum(xp.maximum(omega_out, -bound), bound), omega_out)
    no_speed = (nc_prev == 0) & ~speed_upd

    status = (i32(still) * _I_ST_STANDSTILL
              | i32(dir_last < 0) * _I_ST_REVERSE
              | i32(~hv) * _I_ST_HALL_FAULT
              | i32(jump) * _I_ST_HALL_SEQ
              | i32(unanchored) * _I_ST_NO_ANCHOR
              | i32(qep_err) * _I_ST_QEP_ERROR
              | i32(bounce | reject | (ev & ~speed_upd)) * _I_ST_EDGE_REJECT
              | i32(missing) * _I_ST_MISSING_EDGE
              | i32(dir_mismatch) * _I_ST_DIR_MISMATCH
              | i32(no_speed) * _I_ST_NO_SPEED)

    new = EstimatorState(phase=ph, q=q, n=n, k_last=k_last, dir_last=dir_last, nc_prev=nc_prev,
                         against=against, omega=omega, alpha=alpha, adv=adv, G=G,
                         hall_last=hall_last, sector=sector, anchored=anchored,
                         n_anchor=n_anchor, tick=tick, run=run, R_prev=R_prev, c_tab=c_tab, ts=ts)
    return new, EstimatorOut(theta_hat=theta, omega_hat=omega_out, theta_enc=theta_enc,
                             status=status), sample
