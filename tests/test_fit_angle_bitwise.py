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
