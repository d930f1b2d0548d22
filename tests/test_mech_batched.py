"""The plant's identifier runs its background slice once for a whole batch
(:func:`eol_cal.firmware.mech_tick.batched_background`): the evaluation's arithmetic only on the
ticks some motor needs it. It must give what every motor's own :func:`mech_background` gives, bit
for bit, whichever members are evaluating, checking a mark, clearing or idle.

The power-ups' scan computes the evaluation only for the members that need it, a few at a time
(:func:`eol_cal.firmware.mech_tick.batched_background_few`): the same, but for the score and the
margin, sums over 64 samples that XLA may add in another order for the fewer rows (within 16
units in the last place of binary32 here; 7 the most in tests/test_mech_identify.py's 10 000
power-ups, ``bench/bench_powerups.py --whole``)."""

from __future__ import annotations

import numpy as np
import pytest

from eol_cal.firmware import estimator as est
from eol_cal.firmware import mech_golden as G
from eol_cal.firmware.mech import MechConsts, MechState, block_mech_tables, mech_init, n_slices
from eol_cal.firmware.mech_tick import background_heavy, batched_background, batched_background_few, mech_background

jax = pytest.importorskip("jax")
jnp = jax.numpy


def _batch(n: int, seed: int):
    """(consts, tables, identifier states, estimator states) of ``n`` motors in every phase of the background."""
    block = G.golden_block("mech_a")
    cfg = est.EstimatorConfig.from_block(block)
    mc = MechConsts.of(cfg)
    tb = block_mech_tables(block)
    rng = np.random.default_rng(seed)
    L = n_slices(mc)
    states, ests = [], []
    for i in range(n):
        ms = mech_init(mc.N)._replace(
            acc=rng.normal(0.0, 1e-3, 2 * mc.N).astype(np.float32), cnt=rng.integers(0, 40, 2 * mc.N).astype(np.int32),
            busy=np.int32((0, 1, 2, L, L + 1)[i % 5]), mk=np.int32((0, 1, 2)[i % 3]), clr=np.int32(i % 7 == 6),
            ev_d=np.int32(i % 2), ev_G=np.float32(rng.uniform(-3, 3)), mk_d=np.int32((i // 2) % 2),
            mk_G=np.float32(rng.uniform(-3, 3)), r=np.int32(i % mc.PP), active=np.int32(i % 4 == 0))
        states.append(ms)
        es = est.init_state(cfg, 1, 0, 0)
        ests.append(es._replace(c_tab=rng.normal(0.0, 2e-3, np.shape(es.c_tab)).astype(np.float32)))
    stack = lambda xs: type(xs[0])(*(jnp.asarray(np.stack(f)) for f in zip(*xs, strict=True)))  # noqa: E731
    tbs = type(tb)(*(jnp.asarray(np.stack([f] * n)) for f in tb))
    return mc, tbs, stack(states), stack(ests)


def _same(a: MechState, b: MechState, sums_ulp: int = 0) -> None:
    for name, x, y in zip(a._fields, a, b, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        if name in ("ev_score", "ev_margin") and sums_ulp:
            np.testing.assert_array_max_ulp(x, y, maxulp=sums_ulp)
        else:
            assert np.array_equal(x, y), name


@pytest.mark.parametrize("members", [slice(None), np.array([0, 6, 12])])  # some heavy; none heavy (idle, mk done, clearing)
@pytest.mark.parametrize("width", [None, 2, 8])  # every member; the heavy ones two a round (several rounds), eight
def test_the_batched_background_is_every_motors_own(members, width):
    mc, tb, ms, es = _batch(15, seed=4)
    pick = lambda t: type(t)(*(x[members] for x in t))  # noqa: E731
    tb, ms, es = pick(tb), pick(ms), pick(es)
    heavy = np.asarray(background_heavy(ms))
    assert heavy.any() == isinstance(members, slice) and not heavy.all()
    own = jax.jit(jax.vmap(lambda t, m, s: mech_background(mc, t, m, s, xp=jnp)))(tb, ms, es)
    if width is None:
        batched = jax.jit(lambda t, m, s: batched_background(mc, t, m, s))(tb, ms, es)
    else:
        batched = jax.jit(lambda t, m, s: batched_background_few(mc, t, m, s, width))(tb, ms, es)
    _same(batched, own, sums_ulp=0 if width is None else 16)
    # the slices moved on: the check compares a step that did something
    assert not np.array_equal(np.asarray(own.busy), np.asarray(ms.busy))
