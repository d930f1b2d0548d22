"""The one angle-wrapping rule (eol_cal.numerics.wrap): ranges, exactness in range, numpy and JAX alike."""

import math

import numpy as np

from eol_cal.numerics.wrap import TWO_PI, wrap_2pi, wrap_pi


def test_ranges_and_edges():
    x = np.linspace(-20.0, 20.0, 4001)
    w = wrap_pi(x)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    assert np.allclose(np.sin(w), np.sin(x), atol=1e-12) and np.allclose(np.cos(w), np.cos(x), atol=1e-12)
    assert wrap_pi(-math.pi) == math.pi and wrap_pi(math.pi) == math.pi
    r = wrap_2pi(x)
    assert np.all(r >= 0.0) and np.all(r < TWO_PI) and np.allclose(np.exp(1j * r), np.exp(1j * x))


def test_in_range_angles_come_back_bit_for_bit():
    x = np.random.default_rng(0).uniform(-math.pi, math.pi, 1000)
    assert np.array_equal(wrap_pi(x), x)
    assert all(float(wrap_pi(float(v))) == float(v) for v in x[:50])


def test_jax_and_numpy_agree():
    import jax.numpy as jnp

    x = np.linspace(-9.0, 9.0, 101, dtype=np.float32)
    np.testing.assert_allclose(np.asarray(wrap_2pi(jnp.asarray(x), jnp)), wrap_2pi(x), atol=1e-6)
    np.testing.assert_allclose(np.asarray(wrap_pi(jnp.asarray(x), jnp)), wrap_pi(x), atol=1e-6)
