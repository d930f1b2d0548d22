"""The identifier's two halves (contract revision 1.2, ``firmware_params/MECH.md`` "Per tick" and
"Background"): :func:`mech_tick`, what the 20 kHz interrupt runs, constant work (collect the pitch
sample, apply a finished evaluation or mark check, start the next); :func:`mech_background`, one
bounded slice of the evaluation or of the revolution mark's check, what the background loop runs.

The evaluation works on frozen data: while it runs the tick takes no pitch sample, and it uses the
grid offset ``G`` of the tick that started it; only the estimator's learned edge errors are read
when its first slice runs. Its result is applied by the first tick after its last slice. The
reference (golden vectors, the plant) runs one background slice after every tick
(:func:`mech_step`); here the whole evaluation is computed at its first slice and held for the
others, which gives the C port's slice-by-slice result bit for bit (the later slices read only
frozen data).
"""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="arg-type,operator"

from typing import TypeVar, cast

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.firmware.estimator_config import F32, I32, wrap_pm
from eol_cal.firmware.estimator_step import EstimatorOut, EstimatorState, PitchSample
from eol_cal.firmware.scalar_numpy import SCALAR_NP, numpy_of, when
from eol_cal.firmware.mech import (
    CNT_MAX, SLICE_EDGES, EV_EVAL, EV_IDENTIFIED, EV_PASS, EV_RESET_EVAL, EV_RESET_FAULT, EV_RESET_FRACTION, RESET_STATUS,
    MechConsts, MechOut, MechState, MechTables, evaluate, set_add, f32_, mean_c_of, n_slices,
)
from eol_cal.firmware.mech_params import FP_FORWARD

_F0 = F32(0.0)
_I0 = I32(0)
_FALSE = cast(Array, np.False_)  # typed as the step's arrays
T = TypeVar("T")


def n_clear_slices(mc: MechConsts) -> int:
    """Background slices that clear the samples after a withdrawal (16 entries a slice)."""
    return -(-2 * mc.N // SLICE_EDGES)


def _withdrawn(ms: MechState, N: int, xp: ArrayModule) -> MechState:
    """``ms`` after a withdrawal: nothing identified, accumulated or running (score and margin kept);
    the background clears the samples (``clr``), the tick takes none until it has."""
    z = I32(0) * ms.n_new
    return ms._replace(acc=xp.zeros_like(ms.acc), cnt=xp.zeros_like(ms.cnt), n_new=z, cand=I32(-1) + z, active=z,
                       miss=xp.zeros_like(ms.miss) + I32(N), busy=z, mk=z, clr=z + I32(1))


def mech_tick(mc: MechConsts, tb: MechTables, ms: MechState, es: EstimatorState, eo: EstimatorOut,
              ps: PitchSample, xp: ArrayModule = np, scatter: bool = False) -> tuple[MechState, MechOut]:
    """The interrupt's part of a tick, after the estimator's (MECH.md, "Per tick"): constant work.

    ``es`` is the estimator's state after this tick, ``eo`` its outputs, ``ps`` its pitch sample;
    ``scatter``: a sample's entry of the tables written alone (:func:`eol_cal.firmware.mech.set_add`).
    """
    i32 = xp.int32
    N = mc.N
    enabled, take, fault, done = _tick_flags(mc, tb, ms, eo, ps, xp)
    if xp is SCALAR_NP and not (take or fault or done or ms.mk == 2):
        # one motor, a quiet tick (most): no sample, nothing finished or withdrawn: steps 1 and 2
        # keep the state as it is (the values the selects below give), no event
        new, reset, events = ms, _FALSE, _I0
    else:
        # 1. collect (not while an evaluation reads the samples)
        first = take & (xp.take(ms.cnt, ps.index) == 0)
        if xp is SCALAR_NP and not take:  # one motor, no sample: adding 0 leaves the tables as they are
            acc, cnt, miss = ms.acc, ms.cnt, ms.miss  # (acc never holds -0.0: sums of +0.0 and pitch errors)
        else:
            acc = set_add(ms.acc, ps.index, xp.where(take, ps.error, _F0), xp, scatter)
            cnt = set_add(ms.cnt, ps.index, i32(take), xp, scatter)
            miss = set_add(ms.miss, ps.index % I32(2), -i32(first), xp, scatter)
        n_new = xp.minimum(ms.n_new + i32(take), I32(N))
        # 2. a finished evaluation, a finished mark check
        ok = ms.ev_ok != 0
        passed = done & ok
        confirm = passed & (ms.active == 0) & (ms.cand == ms.ev_r)
        eval_bad = done & (ms.active != 0) & (~ok | (ms.ev_r != ms.r))
        frac_bad = (ms.mk == 2) & (ms.active != 0) & (ms.mk_bad != 0)
        reset = fault | eval_bad | frac_bad
        kept = ms._replace(
            acc=acc, cnt=cnt, miss=miss, n_new=n_new,
            active=xp.where(confirm, I32(1), ms.active), r=xp.where(confirm & ~reset, ms.ev_r, ms.r),
            cand=xp.where(done, xp.where(ok, ms.ev_r, I32(-1)), ms.cand),
            score=xp.where(done, ms.ev_score, ms.score), margin=xp.where(done, ms.ev_margin, ms.margin),
            busy=xp.where(done, I32(0), ms.busy), mk=xp.where(ms.mk == 2, I32(0), ms.mk))
        if xp is SCALAR_NP:  # one motor: the state picked whole, the withdrawn one built only when taken
            new = _withdrawn(kept, N, xp) if reset else kept
        else:
            gone = _withdrawn(kept, N, xp)
            new = MechState(*(xp.where(reset, g, k) for g, k in zip(gone, kept, strict=True)))
        events = (i32(done) * I32(EV_EVAL) | i32(passed) * I32(EV_PASS) | i32(confirm & ~reset) * I32(EV_IDENTIFIED)
                  | i32(fault) * I32(EV_RESET_FAULT) | i32(frac_bad & ~fault) * I32(EV_RESET_FRACTION)
                  | i32(eval_bad & ~fault) * I32(EV_RESET_EVAL))
    d, due, mark = _due_mark(mc, tb, new, es, enabled & ~reset, xp)
    if xp is not SCALAR_NP or due or mark:  # (one motor, neither: the selects keep the state)
        new = new._replace(busy=xp.where(due, I32(1), new.busy), ev_d=xp.where(due, d, new.ev_d),
                           ev_G=xp.where(due, es.G, new.ev_G), n_new=xp.where(due, I32(0), new.n_new),
                           mk=xp.where(mark, I32(1), new.mk), mk_d=xp.where(mark, d, new.mk_d),
                           mk_G=xp.where(mark, es.G, new.mk_G))
    return new, MechOut(active=new.active, r=new.r, events=events, score=new.score, margin=new.margin)


def _tick_flags(mc: MechConsts, tb: MechTables, ms: MechState, eo: EstimatorOut, ps: PitchSample,
                xp: ArrayModule) -> tuple[Array, Array, Array, Array]:
    """(enabled, take: a pitch sample is collected, fault: the estimator's status withdraws,
    done: an evaluation finished) of a tick (MECH.md, "Per tick", steps 1-2)."""
    enabled = tb.enabled != 0
    take = enabled & (ps.learn != 0) & (xp.take(ms.cnt, ps.index) < I32(CNT_MAX)) & (ms.busy == 0) & (ms.clr == 0)
    fault = enabled & ((eo.status & I32(RESET_STATUS)) != 0)
    return enabled, take, fault, ms.busy == I32(n_slices(mc) + 1)


def _due_mark(mc: MechConsts, tb: MechTables, ms: MechState, es: EstimatorState, go: Array,
              xp: ArrayModule) -> tuple[Array, Array, Array]:
    """Steps 3-4 on the state after steps 1-2 (``go``: enabled and not withdrawn this tick):
    (direction d, due: an evaluation starts, mark: the revolution mark's check is asked)."""
    i32 = xp.int32
    # 3. start an evaluation when a revolution of fresh samples is in
    d = i32(es.dir_last < 0)
    has_dir = (tb.dirs & (I32(FP_FORWARD) << d)) != 0
    due = (go & (es.anchored != 0) & (ms.n_new >= I32(mc.N)) & has_dir
           & (xp.take(ms.miss, d) == 0) & (ms.busy == 0) & (ms.clr == 0))
    # 4. ask for the revolution mark's check: an A edge at the firmware's pulse 0
    mark = (tb.enabled != 0) & (ms.active != 0) & (es.n == 0) & ((es.k_last >> I32(2)) == 0) & (ms.mk == 0)
    return d, due, mark


def batched_tick(mc: MechConsts, tb: MechTables, ms: MechState, es: EstimatorState, eo: EstimatorOut,
                 ps: PitchSample, axis_name: str, scatter: bool = False) -> tuple[MechState, MechOut]:
    """:func:`mech_tick` of one member of a batch ``jax.vmap``-ped with ``axis_name`` (JAX): the
    same result, its steps computed on the ticks some member of the batch needs them.

    Most ticks nobody collects a sample, finishes, withdraws, starts an evaluation or reaches a
    revolution mark; then every member's state stays as it is and no event is raised (the values
    :func:`mech_tick`'s selects give), so the batch skips the steps (under ``vmap`` a branch on a
    per-member value computes both sides; the batch's ``any`` is one value for all). ``scatter``:
    as :func:`mech_tick`'s.
    """
    import jax.numpy as jnp

    enabled, take, fault, done = _tick_flags(mc, tb, ms, eo, ps, jnp)
    _, due, mark = _due_mark(mc, tb, ms, es, enabled, jnp)
    need = take | fault | done | (ms.mk == 2) | due | mark
    return when(need, lambda: mech_tick(mc, tb, ms, es, eo, ps, xp=jnp, scatter=scatter),
                lambda: (ms, MechOut(active=ms.active, r=ms.r, events=jnp.zeros_like(ms.active),
                                     score=ms.score, margin=ms.margin)), jnp, axis_name)


def background_heavy(ms: MechState) -> Array:
    """Whether this background call computes something (an evaluation's first slice, a mark check)."""
    return ((ms.busy == 1) | (ms.mk == 1)) & (ms.clr == 0)


def mech_background(mc: MechConsts, tb: MechTables, ms: MechState, es: EstimatorState,
                    xp: ArrayModule = np) -> MechState:
    """One background slice (MECH.md, "Background"): the running evaluation's next slice, else the
    revolution mark's check when one was asked. ``es`` is the estimator's state now."""
    L = n_slices(mc)
    clearing = ms.clr != 0
    running = (ms.busy >= 1) & (ms.busy <= I32(L)) & ~clearing
    do_mark = (ms.mk == 1) & ~running & ~clearing
    axp = numpy_of(xp)  # the evaluation works on whole arrays
    if axp is np and not ((ms.busy == 1 and not clearing) or do_mark):
        return mech_background_idle(mc, ms, xp)
    ok, r, score, margin = evaluate(mc, tb, ms, es.c_tab, ms.ev_G, ms.ev_d, axp)
    first = (ms.busy == 1) & ~clearing
    e_now = wrap_pm(((ms.mk_G + mean_c_of(mc, es.c_tab, ms.mk_d, axp)) - tb.grid_phase) - f32_(ms.r, xp) * mc.DELTA, xp)
    return mech_background_idle(mc, ms, xp)._replace(
        busy=xp.where(running, ms.busy + I32(1), ms.busy),
        ev_ok=xp.where(first, xp.int32(ok), ms.ev_ok), ev_r=xp.where(first, r, ms.ev_r),
        ev_score=xp.where(first, score, ms.ev_score), ev_margin=xp.where(first, margin, ms.ev_margin),
        mk=xp.where(do_mark, I32(2), ms.mk),
        mk_bad=xp.where(do_mark, xp.int32(xp.abs(e_now) > tb.id_frac_tol), ms.mk_bad))


def mech_background_idle(mc: MechConsts, ms: MechState, xp: ArrayModule = np) -> MechState:
    """:func:`mech_background` when :func:`background_heavy` is false: a later slice of a running
    evaluation (its result is already held) or nothing, without the arithmetic."""
    clearing = ms.clr != 0
    running = (ms.busy >= 1) & (ms.busy <= I32(n_slices(mc))) & ~clearing
    if xp is SCALAR_NP and not (running or clearing):  # one motor, nothing running: as it is
        return ms
    clr = xp.where(clearing, xp.where(ms.clr >= I32(n_clear_slices(mc)), I32(0), ms.clr + I32(1)), ms.clr)
    return ms._replace(busy=xp.where(running, ms.busy + I32(1), ms.busy), clr=clr)


def batched_background(mc: MechConsts, tb: MechTables, ms: MechState, es: EstimatorState) -> MechState:
    """:func:`mech_background` of a batch of identifiers (JAX; every array's leading axis the
    batch): the evaluation's arithmetic only on the ticks some member of the batch needs it.

    The same result as the vmapped :func:`mech_background` (which otherwise runs whole every tick:
    under ``vmap`` a branch on a per-member value computes both sides); the heavy ticks are an
    evaluation's first slice and a revolution mark, a few per revolution and member.
    """
    import jax
    import jax.numpy as jnp

    return jax.lax.cond(jnp.any(background_heavy(ms)), lambda: batched_background_all(mc, tb, ms, es),
                        lambda: mech_background_idle(mc, ms, xp=jnp))


def batched_background_all(mc: MechConsts, tb: MechTables, ms: MechState, es: EstimatorState) -> MechState:
    """:func:`mech_background` of every member of a batch (JAX; leading axis the batch): the branch
    :func:`batched_background` takes when some member's :func:`background_heavy` is true."""
    import jax
    import jax.numpy as jnp

    return jax.vmap(lambda t, m, s: mech_background(mc, t, m, s, xp=jnp))(tb, ms, es)


def batched_background_few(mc: MechConsts, tb: MechTables, ms: MechState, es: EstimatorState,
                           width: int) -> MechState:
    """:func:`mech_background` of a batch of identifiers (JAX; every array's leading axis the
    batch): the evaluation's arithmetic only for the members that need it, ``width`` at a time.

    The same result as :func:`batched_background`, but for the evaluation's score and margin: sums
    over fewer rows, which XLA may add in another order (within a few units in the last place;
    tests/test_mech_batched.py). A batch of hundreds (the power-ups') has some
    member's heavy tick on a good part of its ticks, where :func:`batched_background` computes
    every member's evaluation; here the members whose :func:`background_heavy` is true are
    gathered, ``width`` a round (rarely more than one), computed and written back. Gathers and
    scatters keep a loop from XLA's single kernel (:mod:`eol_cal.numerics.xla`): for a scan that is
    a sequence of XLA's operations anyway.
    """
    import jax
    import jax.numpy as jnp

    size = jnp.shape(ms.active)[0]

    def rows(tree: T, idx: jax.Array) -> T:
        return jax.tree.map(lambda x: x.at[idx].get(mode="fill", fill_value=0), tree)

    def round_(carry: tuple[MechState, jax.Array]) -> tuple[MechState, jax.Array]:
        out, left = carry
        idx = jnp.nonzero(left, size=width, fill_value=size)[0]  # past the end: read as 0, not written
        new = batched_background_all(mc, rows(tb, idx), rows(ms, idx), rows(es, idx))
        # only the members' own numbers are written back: the samples' tables are the background's to read
        out = MechState(*(o if jnp.ndim(o) > 1 else jnp.asarray(o).at[idx].set(n, mode="drop")
                          for o, n in zip(out, new, strict=True)))
        return out, left.at[idx].set(False, mode="drop")

    heavy = background_heavy(ms)
    idle = mech_background_idle(mc, ms, xp=jnp)
    return jax.lax.cond(jnp.any(heavy), lambda: jax.lax.while_loop(lambda c: jnp.any(c[1]), round_, (idle, heavy))[0],
                        lambda: idle)


def mech_step(mc: MechConsts, tb: MechTables, ms: MechState, es: EstimatorState, eo: EstimatorOut,
              ps: PitchSample, xp: ArrayModule = np) -> tuple[MechState, MechOut]:
    """One tick of the identifier after the estimator's, then one background slice: the schedule the
    golden vectors and the plant assume (MECH.md, "Background")."""
    ms, mo = mech_tick(mc, tb, ms, es, eo, ps, xp)
    return mech_background(mc, tb, ms, es, xp), mo
