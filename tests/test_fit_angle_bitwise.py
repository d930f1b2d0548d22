"""The refit's speed-ups that must not move a result (issue 37 item 2): the fingerprint's hall
orders read the positions at the samples around each hall transition only
(:func:`eol_cal.analysis.fit.fp_angle.bracketing_samples`), which ``np.interp`` must give bit for
bit as from every sample, at sample times, between them, on the ends and outside."""

from __future__ import annotations

import numpy as np

from eol_cal.analysis.fit.fp_angle import boundary_position, bracketing_samples


def test_interp_over_the_bracketing_samples_is_interp_over_every_sample():
    rng = np.random.default_rng(37)
    t = np.cumsum(rng.uniform(0.5e-4, 1.5e-4, 5000))
    q = np.cumsum(rng.integers(-1, 2, len(t)))
    theta = np.cumsum(rng.normal(0.01, 0.003, len(t)))
    t_q = np.concatenate((rng.uniform(t[0] - 1e-3, t[-1] + 1e-3, 300), t[[0, 1, 17, 2500, -2, -1]],
                          [t[0] - 1.0, t[-1] + 1.0]))
    i = bracketing_samples(t, t_q)
    assert np.all(np.diff(i) > 0) and i[0] == 0 and i[-1] == len(t) - 1
    assert len(i) < len(t) // 5  # the point: far fewer samples than the window's
    full = np.interp(t_q, t, boundary_position(q, 3, 0.4, theta, 8, 64))
    sub = np.interp(t_q, t[i], boundary_position(q[i], 3, 0.4, theta[i], 8, 64))
    assert np.array_equal(full, sub)
    assert np.array_equal(np.interp(t_q, t, theta), np.interp(t_q, t[i], theta[i]))


def test_order_columns_are_the_orders_cos_and_sin_within_rounding():
    # the angle correction's mechanical orders as powers of one exp(i phi) (issue 37): the cos and
    # sin of each order within a few ulp over a window's positions (a few revolutions either way;
    # far out cos(m phi) itself is only as exact as the rounding of m phi), in the orders' order
    from eol_cal.analysis.fit.fp_angle import order_columns

    N = 64
    x = np.concatenate((np.random.default_rng(5).uniform(-4 * N * 3, 4 * N * 3, 2000), [0.0, 1.0, 4 * N]))
    phi = 2 * np.pi * x / (4 * N)
    for orders in ((1, 2), (2,), (1,), (1, 3), (2, 1)):
        got = order_columns(x, orders, N)
        want = np.column_stack([f(m * phi) for m in orders for f in (np.cos, np.sin)])
        assert got.shape == want.shape and np.allclose(got, want, rtol=0.0, atol=1e-14)
    assert order_columns(x, (), N).shape == (len(x), 0)
