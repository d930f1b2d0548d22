"""The same step under jax.numpy (lax.scan, vmap) as under numpy, and the signal model in both."""

from __future__ import annotations

import math

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

from eol_cal.firmware import estimator as est  # noqa: E402
from eol_cal.firmware import estimator_golden as G  # noqa: E402
from eol_cal.firmware.kinematics import draw_sensor_errors, encoder_hall_signals  # noqa: E402


def _ang_diff(x, y):
    return np.abs(np.angle(np.exp(1j * (np.asarray(x, np.float64) - np.asarray(y, np.float64)))))


def test_numpy_and_jax_scan_agree_paper():
    # 3000 ticks of the edge-bounce scenario: start-up, anchoring, a bounce, steady tracking
    cfg = est.EstimatorConfig.paper()
    a, b, h = (x[:3000] for x in G.SCENARIOS["estimator_edge_bounce.csv"].signals())
    ref = est.run(cfg, a, b, h)
    out = est.run_jax(cfg, a, b, h)
    assert np.max(_ang_diff(out.theta_hat, ref.theta_hat)) < 1e-4
    assert np.max(_ang_diff(out.theta_enc, ref.theta_enc)) < 1e-4
    assert np.max(np.abs(np.asarray(out.omega_hat) - ref.omega_hat)) < 1e-3
    assert np.array_equal(np.asarray(out.status), ref.status)


@pytest.mark.slow
def test_best_under_jit_vmap_scan_with_the_jax_signal_model():
    # every improvement (learned tables in the scan carry), two motors batched with vmap, the
    # signals made by the signal model under jax.numpy inside the same jit
    cfg = est.EstimatorConfig.all_improvements()
    errors = [draw_sensor_errors(np.random.default_rng(s), 64) for s in (1, 2)]
    t = np.arange(6000) / G.TICK_HZ
    theta_m = np.mod(0.3 + 8 * math.pi * t, 2 * math.pi)  # 240 rpm: learning starts after 0.25 s

    def one(err):
        a, b, h = encoder_hall_signals(jnp.asarray(theta_m, jnp.float32), 6, 64, err, xp=jnp)
        s0 = est.init_state(cfg, h[0], a[0], b[0], xp=jnp)

        def body(s, x):
            return est.step(cfg, s, x[0], x[1], x[2], xp=jnp)

        return jax.lax.scan(body, s0, jnp.stack([a, b, h], axis=-1))[1]

    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *errors)
    out = jax.jit(jax.vmap(one))(stacked)
    assert out.theta_hat.shape == (2, 6000) and out.theta_hat.dtype == jnp.float32
    for i, err in enumerate(errors):
        a, b, h = encoder_hall_signals(theta_m, 6, 64, err)
        ref = est.run(cfg, a, b, h)
        assert np.max(_ang_diff(out.theta_hat[i], ref.theta_hat)) < 1e-4
        assert np.max(np.abs(np.asarray(out.omega_hat[i]) - ref.omega_hat)) < 1e-2
        assert np.array_equal(np.asarray(out.status[i]), ref.status)


def test_signal_model_numpy_and_jax_agree():
    err = draw_sensor_errors(np.random.default_rng(5), 64)
    theta_m = np.linspace(0.0, 2 * math.pi, 8001)[:-1]
    ref = encoder_hall_signals(theta_m, 6, 64, err)
    got = encoder_hall_signals(jnp.asarray(theta_m, jnp.float32), 6, 64, err, xp=jnp)
    for r, g in zip(ref, got, strict=True):
        # float32 positions may flip a level on the sample nearest a switching point
        assert np.count_nonzero(np.asarray(g) != r) <= 4


def test_chunked_hall_table_is_a_dynamic_argument(monkeypatch):
    # a calibrated hall table (two entries moved) runs in the nominal table's compiled program
    # and gives what the numpy reference gives with a config carrying that table
    from eol_cal.numerics import exported

    monkeypatch.setattr(exported, "_DIR", None)  # the traced programs counted, none read from a cache
    nominal = est.EstimatorConfig.paper()
    skewed = list(est.NOMINAL_HALL_ANGLE)
    skewed[0] += math.radians(4.0)
    skewed[3] -= math.radians(3.0)
    cfg_skew = est.EstimatorConfig.paper(hall_angle=skewed)
    err = draw_sensor_errors(np.random.default_rng(3), 64)
    t = np.arange(6000) / G.TICK_HZ
    a, b, h = encoder_hall_signals(np.mod(0.3 + 4 * math.pi * t, 2 * math.pi), 6, 64, err)  # 120 rpm
    ref = est.run(cfg_skew, a, b, h)
    ref_nominal = est.run(nominal, a, b, h)
    est._scan_chunk.cache_clear()
    got_nominal = est.run_jax_chunked(nominal, a, b, h)
    got = est.run_jax_chunked(nominal, a, b, h, hall_angle=skewed)
    for out, r in ((got, ref), (got_nominal, ref_nominal)):
        assert np.max(_ang_diff(out.theta_hat, r.theta_hat)) < 1e-4
        assert np.max(_ang_diff(out.theta_enc, r.theta_enc)) < 1e-4
        assert np.max(np.abs(out.omega_hat - r.omega_hat)) < 1e-3
        assert np.array_equal(out.status, r.status)
    # the table matters (the moved entries shift the anchor by degrees) ...
    assert np.max(_ang_diff(got.theta_hat, got_nominal.theta_hat)) > math.radians(2.0)
    # ... and is not part of the program: one compiled scan for both tables and for cfg_skew's own
    assert est.run_jax_chunked(cfg_skew, a, b, h).theta_hat == pytest.approx(got.theta_hat, abs=1e-6)
    assert est._scan_chunk.cache_info().currsize == 1
    assert est._scan_chunk(est._program_config(cfg_skew))._cache_size() == 1
    # run_jax takes it the same way
    out = est.run_jax(nominal, a[:3000], b[:3000], h[:3000], hall_angle=skewed)
    assert np.max(_ang_diff(out.theta_hat, ref.theta_hat[:3000])) < 1e-4


@pytest.mark.parametrize("improvements", [
    {}, pytest.param({"learn_pitch_errors": True, "accel_prediction": True}, marks=pytest.mark.slow)])
def test_batch_is_each_capture_alone_bit_for_bit(improvements):
    # captures of different lengths, speeds and hall tables side by side in one batched scan give
    # exactly what each gives alone (the lanes share nothing); the learned-table option included,
    # whose table update is a select under JAX (a scatter once vmapped would leave the tick loop)
    cfg = est.EstimatorConfig.paper(**improvements)
    skewed = list(est.NOMINAL_HALL_ANGLE)
    skewed[2] += math.radians(3.0)
    signals, tables = [], []
    for k, (rpm, n) in enumerate([(120.0, 5000), (240.0, 7321), (-60.0, 4100)]):
        err = draw_sensor_errors(np.random.default_rng(10 + k), 64)
        t = np.arange(n) / G.TICK_HZ
        signals.append(encoder_hall_signals(np.mod(0.2 * k + rpm / 30.0 * math.pi * t, 2 * math.pi), 6, 64, err))
        tables.append(skewed if k == 1 else None)
    batch = est.run_jax_batch(cfg, signals, tables, chunk=1024)
    assert [len(o.theta_hat) for o in batch] == [5000, 7321, 4100]
    for (a, b, h), table, got in zip(signals, tables, batch, strict=True):
        alone = est.run_jax_chunked(cfg, a, b, h, chunk=1024, hall_angle=table)
        for x, y in zip(got, alone, strict=True):
            np.testing.assert_array_equal(x, y)
        ref = est.run(est.EstimatorConfig.paper(hall_angle=table or est.NOMINAL_HALL_ANGLE, **improvements), a, b, h)
        assert np.array_equal(got.status, ref.status)
        assert np.max(_ang_diff(got.theta_hat, ref.theta_hat)) < 1e-4
    # the batch's A edge events and hall re-anchors run only on the ticks some lane has one
    # (LANE_AXIS): what the plain vmapped scan, which runs them on every tick, gives, bit for bit
    n = min(len(a) for a, _, _ in signals)
    stacked = [np.stack([x[i][:n] for x in signals]) for i in range(3)]
    plain = est.run_jax(cfg, *stacked)
    for i, got in enumerate(est.run_jax_batch(cfg, [tuple(x[i] for x in stacked) for i in range(3)], chunk=1024)):
        for x, y in zip(got, plain, strict=True):
            np.testing.assert_array_equal(x, np.asarray(y)[i])
    # more captures than the widest program: split into batches, the same figures
    many = est.run_jax_batch(cfg, signals * 30, tables * 30, chunk=1024)
    assert len(many) == 90 and est.JAX_LANES[-1] < 90
    for got, alone in zip(many[-3:], batch, strict=False):
        np.testing.assert_array_equal(got.theta_hat, alone.theta_hat)
