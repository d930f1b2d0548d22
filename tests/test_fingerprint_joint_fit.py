"""The fingerprint's joint fit (each stretch's motion projected out, normal equations summed per
pulse) against the dense least squares over every edge: the same edge errors, variances, residual
and degrees of freedom."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.analysis import fingerprint as fpr
from eol_cal.firmware.mech_params import FP_FORWARD

N, POLES = 64, 8
QUARTER = POLES * math.pi / N / 4.0


def _stretches(rng: np.random.Generator, fp_true: np.ndarray, n: int, reverse: bool) -> list:
    """Stretches of A edges of a shaft turning smoothly (each its own speed, acceleration and
    start), edge k seen at the angle k*quarter + the fingerprint's error, plus noise."""
    out = []
    for _ in range(n):
        k0 = int(rng.integers(0, 4 * N)) * 4 + 1
        n_pulses = int(rng.integers(N + N // 2, 3 * N))
        k = k0 + 2 * np.arange(2 * n_pulses)  # A rising (4m+1) and falling (4m+3) edges
        if reverse:
            k = k[::-1]
        err = fp_true[(k >> 1) % (2 * N)]
        angle = k * QUARTER + err + rng.normal(0, 2e-4, len(k))
        w, a = rng.uniform(50, 150), rng.uniform(-20, 20)  # rad/s, rad/s^2
        s = np.abs(angle - angle[0])
        t = (np.sqrt(w * w + 2 * a * s) - w) / a  # s = w t + a t^2 / 2
        out.append((t, k))
    return out


def _dense(stretches: list, dirs: list[int]):
    """The joint fit as one dense least-squares problem (numpy lstsq on the full design matrix)."""
    P = fpr._low_order_complement(N)
    nF = P.shape[1]
    deg1 = fpr._POLY_DEGREE + 1
    nb = deg1 * len(stretches)
    col = {d: nb + i * nF for i, d in enumerate(dirs)}
    rows, rhs = [], []
    for g, (times, k) in enumerate(stretches):
        half = (k >> 1) & 1
        x = (times - times[0]) / (times[-1] - times[0]) * 2.0 - 1.0
        A = np.zeros((len(times), nb + nF * len(dirs)))
        A[:, g * deg1:(g + 1) * deg1] = np.polynomial.legendre.legvander(x, fpr._POLY_DEGREE)
        for d in dirs:
            sel = half == d
            A[sel, col[d]:col[d] + nF] = -P[(k[sel] >> 2) % N]
        rows.append(A)
        rhs.append(k * QUARTER)
    A, phi = np.concatenate(rows), np.concatenate(rhs)
    sol = np.linalg.lstsq(A, phi, rcond=None)[0]
    resid = phi - A @ sol
    rss = float(resid @ resid)
    C = rss / (len(phi) - A.shape[1]) * np.linalg.pinv(A.T @ A)
    fp, var = np.full(2 * N, np.nan), np.full(2 * N, np.nan)
    for d in dirs:
        c = slice(col[d], col[d] + nF)
        fp[d::2] = P @ sol[c]
        var[d::2] = np.einsum("ij,jk,ik->i", P, C[c, c], P)
    return fp, var, rss, len(phi) - A.shape[1]


@pytest.mark.parametrize("seed", [1, 2])
def test_the_joint_fit_equals_the_dense_least_squares(seed):
    rng = np.random.default_rng(seed)
    fp_true = rng.normal(0, 3e-3, 2 * N)
    stretches = _stretches(rng, fp_true, 3, False) + _stretches(rng, fp_true, 2, True)
    fp, var, rss, dirs, dof = fpr._joint_fit(stretches, N, QUARTER)
    assert dirs == FP_FORWARD | (FP_FORWARD << 1)
    fp_d, var_d, rss_d, dof_d = _dense(stretches, [0, 1])
    assert dof == dof_d
    np.testing.assert_allclose(fp, fp_d, rtol=0, atol=1e-9)
    np.testing.assert_allclose(var, var_d, rtol=1e-6)
    assert rss == pytest.approx(rss_d, rel=1e-6)
    # and it finds the errors: the true ones less their orders 0..2, which the fit cannot see
    P = fpr._low_order_complement(N)
    for d in (0, 1):
        seen = P @ (P.T @ fp_true[d::2])
        assert np.max(np.abs(fp[d::2] - seen)) < 2e-4
    # a placement trial needs only the residual
    fp2, var2, rss2, _, _ = fpr._joint_fit(stretches, N, QUARTER, cov=False)
    np.testing.assert_array_equal(fp2, fp)
    assert np.isnan(var2).all() and rss2 == rss
