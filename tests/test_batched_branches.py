"""The plant's batch-level branches (``step_pitch(batch_axis=...)``, ``mech_tick.batched_tick``): a
batch ``vmap``-ped with an axis name skips the A edge event, the hall re-anchor and the identifier's
interrupt part on the ticks no member needs them. Every state and output must be what the plain
vmapped steps give, bit for bit, through identifications.

The power-ups' scan (:mod:`eol_cal.firmware.mech_sim`) writes the tables' entries by scatters and
computes the background's evaluation only for the members that need it
(``batched_background_few``): the same again, but for the evaluation's score and margin, which may
differ in the last places of binary32 (sums XLA adds in another order for fewer rows)."""

from __future__ import annotations

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

from eol_cal.firmware import estimator as est  # noqa: E402
from eol_cal.firmware import mech_golden as G  # noqa: E402
from eol_cal.firmware.estimator_step import step_pitch  # noqa: E402
from eol_cal.firmware.mech import EV_IDENTIFIED, MechConsts, block_mech_tables, mech_init  # noqa: E402
from eol_cal.firmware.mech_tick import batched_background, batched_background_few, batched_tick, mech_tick  # noqa: E402

AXIS = "members"


def _run(form: str, cfg, mc, tb, signals):
    """``form``: "plain" (vmapped steps), "branched" (the plant's), "powerups" (the power-ups' scan's)."""
    a, b, h = (jnp.asarray(np.stack(x), jnp.int32) for x in zip(*signals, strict=True))
    n = a.shape[0]
    es0 = jax.vmap(lambda h0, a0, b0: est.init_state(cfg, h0, a0, b0, xp=jnp))(h[:, 0], a[:, 0], b[:, 0])
    ms0 = jax.tree_util.tree_map(lambda x: jnp.stack([jnp.asarray(x)] * n), mech_init(mc.N))

    def member(es, ms, ai, bi, hi):
        if form != "plain":
            scatter = form == "powerups"
            es, eo, ps = step_pitch(cfg, es, ai, bi, hi, xp=jnp, batch_axis=AXIS, scatter_tables=scatter)
            ms, mo = batched_tick(mc, tb, ms, es, eo, ps, AXIS, scatter=scatter)
        else:
            es, eo, ps = step_pitch(cfg, es, ai, bi, hi, xp=jnp)
            ms, mo = mech_tick(mc, tb, ms, es, eo, ps, xp=jnp)
        return es, ms, (eo, ps, mo)

    def body(carry, x):
        es, ms = carry
        es, ms, out = jax.vmap(member, axis_name=AXIS)(es, ms, *x)
        tbs = jax.tree_util.tree_map(lambda t: jnp.stack([jnp.asarray(t)] * n), tb)
        if form == "powerups":
            return (es, batched_background_few(mc, tbs, ms, es, 2)), out
        return (es, batched_background(mc, tbs, ms, es)), out

    carry, outs = jax.jit(lambda c, xs: jax.lax.scan(body, c, xs))((es0, ms0), (a.T, b.T, h.T))
    return jax.tree_util.tree_map(np.asarray, (carry, outs))


@pytest.mark.slow  # three scans of 14 000 ticks compiled, seconds on a quiet machine
def test_the_batch_branches_give_the_plain_steps_bit_for_bit():
    names = ("mech_pole_pair_0.csv", "mech_pole_pair_1.csv", "mech_pole_pair_2.csv")
    block = G.golden_block(G.SCENARIOS[names[0]].block_id)
    cfg = est.EstimatorConfig.from_block(block, standstill_s=1.0)
    mc, tb = MechConsts.of(cfg), block_mech_tables(block)
    signals = [G.SCENARIOS[n].signals() for n in names]
    plain = _run("plain", cfg, mc, tb, signals)
    branched = _run("branched", cfg, mc, tb, signals)
    powerups = _run("powerups", cfg, mc, tb, signals)
    events = plain[1][2].events
    assert np.all(np.any(events & EV_IDENTIFIED, axis=0))  # every member identified on the way
    flat_p, tree_p = jax.tree_util.tree_flatten(plain)
    flat_b, tree_b = jax.tree_util.tree_flatten(branched)
    assert tree_p == tree_b
    for p, b in zip(flat_p, flat_b, strict=True):
        assert p.dtype == b.dtype and p.shape == b.shape
        assert p.tobytes() == b.tobytes()
    # the power-ups' form: every integer (offsets, events, counts, states) the same, the sums' floats
    # within a few units in the last place
    flat_q, tree_q = jax.tree_util.tree_flatten(powerups)
    assert tree_q == tree_p
    for (path, p), q in zip(jax.tree_util.tree_flatten_with_path(plain)[0], flat_q, strict=True):
        if p.dtype.kind == "f" and any(getattr(k, "name", None) in ("score", "margin", "ev_score", "ev_margin") for k in path):
            np.testing.assert_array_max_ulp(p, q, maxulp=16)
        else:
            assert p.tobytes() == q.tobytes(), jax.tree_util.keystr(path)
