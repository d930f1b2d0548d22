"""Compensator: tables vs the analytic i_qc, the firmware evaluation's edge cases, numpy vs jax."""

from __future__ import annotations


import numpy as np
import pytest

from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware import compensator as comp
from eol_cal.firmware import golden

KT = 0.04905
RIPPLE = dict(c6=0.012, phase_c6=0.35, k6=0.0015, phase_k6=-0.6, kt=KT)
HARM = ((12, 0.004, 0.5, 0.0006, -1.0), (18, 0.001, -2.0, 0.0002, 0.7))


def _eval(theta, omega, i_qo, tc, tp, lead=0.0, limit=100.0):
    return comp.i_qc(np.float32(theta), np.float32(omega), np.float32(i_qo), tc, tp, lead, limit)


@pytest.mark.parametrize("harmonics", [(), HARM])
def test_table_nodes_equal_analytic_within_binary32_rounding(harmonics):
    n = 256
    tc, tp = comp.make_tables(N=n, harmonics=harmonics, **RIPPLE)
    assert tc.dtype == tp.dtype == np.float32 and tc.shape == (n,)
    theta_j = 2 * np.pi * np.arange(n) / (6 * n)
    for i_qo in (-20.0, 0.0, 7.5):
        want = comp.ripple_i_qc(theta_j, i_qo, harmonics=harmonics, **RIPPLE)
        got = tc.astype(np.float64) + i_qo * tp.astype(np.float64)
        scale = np.abs(comp.ripple_parts(theta_j, harmonics=harmonics, **RIPPLE)[0]).max() \
            + abs(i_qo) * np.abs(comp.ripple_parts(theta_j, harmonics=harmonics, **RIPPLE)[1]).max()
        assert np.max(np.abs(got - want)) <= 2 * np.finfo(np.float32).eps * scale


@pytest.mark.parametrize("n", [16, 256, 1024])
def test_evaluation_matches_analytic_within_interpolation_and_rounding(n):
    tc, tp = comp.make_tables(N=n, harmonics=HARM, **RIPPLE)
    rng = np.random.default_rng(n)
    theta = rng.uniform(-10, 10, 4000).astype(np.float32)
    omega = rng.uniform(-2000, 2000, 4000).astype(np.float32)
    i_qo = rng.uniform(-50, 50, 4000).astype(np.float32)
    lead = np.float32(3e-4)
    got = comp.i_qc(theta, omega, i_qo, tc, tp, lead, 1e9)
    assert got.dtype == np.float32
    angle = theta.astype(np.float64) + omega.astype(np.float64) * float(lead)
    want = comp.ripple_i_qc(angle, i_qo, harmonics=HARM, **RIPPLE)
    # linear interpolation of sin(m*x) with step h = 2*pi/N: error <= amp * (m*h)^2 / 8 per harmonic
    h = 2 * np.pi / n
    amps = [(RIPPLE["c6"] + 50 * RIPPLE["k6"], 1)] + [(c + 50 * k, order // 6) for order, c, _, k, _ in HARM]
    interp = sum(a / KT * (m * h) ** 2 / 8 for a, m in amps)
    rounding = 1e-5 * (1 + np.abs(angle).max())  # binary32 angle: ulp(t) * slope
    err = np.abs(got - want)
    assert err.max() <= interp + rounding
    if n == 1024:
        assert err.max() < 2e-4  # and the bound above is not vacuous for fine tables


def test_reduction_wraps_negative_and_large_angles():
    n = 64
    tc, tp = comp.make_tables(N=n, **RIPPLE)
    period = np.float32(2 * np.pi / 6)
    for theta in (0.3, 1.9, 5.0):
        base = _eval(theta, 0, 3.0, tc, tp)
        for k in (-12, -1, 1, 6, 30):
            shifted = np.float32(theta + k * float(period))
            assert abs(_eval(shifted, 0, 3.0, tc, tp) - base) < 5e-5 * (1 + abs(k))


def test_tiny_negative_angle_rounds_to_n_and_maps_to_entry_zero():
    n = 256
    tc, tp = comp.make_tables(N=n, **RIPPLE)
    v = np.float32(-1e-9) * (np.float32(n) * comp.K_6_OVER_2PI)
    u = v - np.floor(v * np.float32(1 / n)) * np.float32(n)
    assert u == np.float32(n)  # the reduction really hits N in binary32
    for theta in (-1e-9, -1e-30, -0.0):
        assert _eval(theta, 0, 2.0, tc, tp) == np.float32(tc[0] + np.float32(2.0) * tp[0])


def test_lead_clamp_and_sign_symmetry():
    n = 256
    tc, tp = comp.make_tables(N=n, **RIPPLE)
    # lead: looking up at theta + omega*lead equals looking up at the advanced angle
    assert abs(_eval(0.5, 400.0, 3.0, tc, tp, lead=1e-3) - _eval(0.9, 0, 3.0, tc, tp)) < 1e-5
    # clamp both signs, exact limit values
    limit = np.float32(0.1)
    vals = comp.i_qc(np.linspace(0, 1.1, 200, dtype=np.float32), np.float32(0), np.float32(60), tc, tp, 0, limit)
    assert vals.max() == limit and vals.min() == -limit
    # i_qo enters linearly: per-amp part flips with its sign
    a, b, c = (_eval(0.2, 0, i, tc, tp) for i in (-4.0, 0.0, 4.0))
    assert abs((c - b) + (a - b)) < 1e-6 and abs(c - b) > 1e-3


def test_block_i_qc_respects_comp_enable():
    b = golden.paper_block()
    theta = np.linspace(0, 6, 50, dtype=np.float32)
    on = comp.block_i_qc(b, theta, np.float32(100), np.float32(5))
    assert np.any(on != 0)
    import dataclasses

    off = comp.block_i_qc(dataclasses.replace(b, flags=B.FLAG_INTERP_ENABLE), theta, np.float32(100), np.float32(5))
    assert np.all(off == 0) and off.shape == on.shape


def test_make_tables_refusals():
    with pytest.raises(InputError, match="table_len"):
        comp.make_tables(N=100, **RIPPLE)
    with pytest.raises(InputError, match="harmonics"):
        comp.make_tables(N=16, harmonics=((9, 1, 0, 0, 0),), **RIPPLE)
    with pytest.raises(InputError, match="harmonics"):
        comp.make_tables(N=16, harmonics=((48, 1, 0, 0, 0),), **RIPPLE)  # 8th table harmonic, N/2 = 8
    with pytest.raises(InputError, match="kt"):
        comp.make_tables(N=16, **{**RIPPLE, "kt": 0.0})


def test_jax_matches_numpy():
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    b = golden.golden_blocks()[2][1]
    rng = np.random.default_rng(7)
    theta = rng.uniform(0, 2 * np.pi, 5000).astype(np.float32)
    omega = rng.uniform(-3000, 3000, 5000).astype(np.float32)
    i_qo = rng.uniform(-80, 80, 5000).astype(np.float32)
    ref = comp.i_qc(theta, omega, i_qo, b.table_const, b.table_per_amp, b.lead_s, b.iqc_limit)
    eager = comp.i_qc(theta, omega, i_qo, b.table_const, b.table_per_amp, b.lead_s, b.iqc_limit, xp=jnp)
    assert np.array_equal(np.asarray(eager), ref)  # same binary32 ops without XLA fusion: bit-exact

    def body(carry, x):
        th, om, iq = x
        return carry, comp.i_qc(th, om, iq, b.table_const, b.table_per_amp, b.lead_s, b.iqc_limit, xp=jnp)

    _, scanned = jax.jit(lambda *a: jax.lax.scan(body, 0.0, a))(theta, omega, i_qo)
    vmapped = jax.jit(jax.vmap(lambda th, om, iq: body(0, (th, om, iq))[1]))(theta, omega, i_qo)
    # XLA may fuse multiply-add (FMA): the angle moves by <= half an ulp of t (~5e-7 rad at 8 rad)
    # times the slope of i_qc (<= ~20 A/rad here), plus a few ulp of the result
    for got in (np.asarray(scanned), np.asarray(vmapped)):
        assert got.dtype == np.float32
        assert np.max(np.abs(got - ref)) <= 2e-5
