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


def test_the_segments_corrected_in_one_pass_as_one_by_one(monkeypatch):
    """fp_angle._correct_segments corrects every segment's angle in one pass over the serial's
    samples (issue 37): each segment's corrected angle is the one the segment-by-segment loop gave,
    bit for bit (the positions, the table and the orders' columns are elementwise; each segment's
    product with the orders' coefficients is its own)."""
    from eol_cal.analysis.fit import fp_angle
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.capture.synthetic import synthetic_capture

    def one_by_one(mi, prints, fp, frac, low):
        out = []
        for s, info in enumerate(mi.info):
            ci = mi.capture_of_segment[s]
            if prints[ci] is None or fp.offsets[ci] is None:
                out.append(None)
                continue
            theta = np.asarray(mi.segments.theta[s], dtype=float) - frac[ci]
            x = boundary_position(prints[ci].q[info.start:info.stop], fp.offsets[ci], fp.grid_phase,
                                  theta + mi.frame_offset_rad, mi.poles, mi.encoder_ppr)
            corr = fp_angle.boundary_interp(x, fp.fp, mi.encoder_ppr)
            if low is not None:
                corr = corr - fp_angle.order_columns(x, low[0], mi.encoder_ppr) @ low[1]
            out.append(theta + corr)
        return out

    seen = []
    batched = fp_angle._correct_segments

    def both(mi, prints, fp, frac, low):
        want = one_by_one(mi, prints, fp, frac, low)
        n = batched(mi, prints, fp, frac, low)
        seen.append((n, low is not None))
        for s, w in enumerate(want):
            if w is not None:
                assert np.array_equal(mi.segments.theta[s], w)
        assert n == sum(w is not None for w in want)
        return n

    monkeypatch.setattr(fp_angle, "_correct_segments", both)
    points = [(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]
    caps = [synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=40 + j, theta_r0=0.7 * j, serial="S1")
            for j, (rpm, iq) in enumerate(points)]  # bench/bench_refit.py's serial
    motor_inputs(caps)
    assert seen == [(6, True)]  # every segment corrected, the orders measured
