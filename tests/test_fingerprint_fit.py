"""The fingerprint's joint fit (per-pulse sums, windows moved by rolling them) against a plain
dense least squares over every edge, and window placement over the pole-pair offsets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.analysis import fingerprint as fpr

N, POLES = 64, 8
QUARTER = POLES * math.pi / N / 4.0
DELTA = 4 * QUARTER


def _true_fingerprint(seed: int) -> np.ndarray:
    """(2N,) edge errors (rad electrical) without mechanical orders 0..2 in either half."""
    P = fpr._low_order_complement(N)
    rng = np.random.default_rng(seed)
    fp = np.zeros(2 * N)
    for d in (0, 1):
        fp[d::2] = P @ (P.T @ rng.normal(0.0, 5e-3, N))
    return fp


def _stretch(fp: np.ndarray, k0: int, n_edges: int, rpm: float, seed: int, noise_s: float = 2e-6):
    """A stretch of A edges (both halves, forward) from boundary ``k0``: the rotor's electrical
    angle at edge k is ``k * QUARTER + fp[(k >> 1) mod 2N]``, a slowly accelerating motion."""
    rng = np.random.default_rng(seed)
    k = k0 + 2 * np.arange(n_edges)  # A edges (k0 odd): every other boundary, k = 4m + 1 and 4m + 3
    theta = k * QUARTER + fp[(k >> 1) % (2 * N)]
    w = rpm / 60.0 * 2 * math.pi * POLES / 2  # rad electrical / s
    # theta = w t + a t^2 / 2, a small: t from the quadratic
    a = 0.05 * w
    t = (-w + np.sqrt(w * w + 2 * a * (theta - theta[0]))) / a
    return t + rng.normal(0.0, noise_s, len(t)), k.astype(np.int64)


def _dense(stretches, halves):
    """The same least squares, plainly: every edge a row; a degree-5 polynomial per stretch and
    the errors in the basis P per kept half as columns."""
    P = fpr._low_order_complement(N)
    nF, deg = P.shape[1], fpr._POLY_DEGREE
    rows_L, rows_A, ys = [], [], []
    n_poly = (deg + 1) * len(stretches)
    for j, (t, k) in enumerate(stretches):
        keep = np.isin((k >> 1) & 1, halves)
        t, k = t[keep], k[keep]
        x = (t - t[0]) / (t[-1] - t[0]) * 2 - 1
        L = np.zeros((len(t), n_poly))
        L[:, j * (deg + 1):(j + 1) * (deg + 1)] = np.polynomial.legendre.legvander(x, deg)
        A = np.zeros((len(t), nF * len(halves)))
        for i, h in enumerate(halves):
            sel = ((k >> 1) & 1) == h
            A[sel, i * nF:(i + 1) * nF] = P[(k[sel] >> 2) % N]
        rows_L.append(L)
        rows_A.append(A)
        ys.append(k * QUARTER)
    X = np.concatenate([np.concatenate(rows_L), -np.concatenate(rows_A)], axis=1)
    y = np.concatenate(ys)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    res = y - X @ coef
    rss = float(res @ res)
    dof = len(y) - X.shape[1]
    C = rss / dof * np.linalg.inv(X.T @ X)[n_poly:, n_poly:]
    fp, var = np.full(2 * N, np.nan), np.full(2 * N, np.nan)
    for i, h in enumerate(halves):
        s = slice(i * nF, (i + 1) * nF)
        fp[h::2] = P @ coef[n_poly:][s]
        var[h::2] = np.diag(P @ C[s, s] @ P.T)
    return fp, var, rss, dof


@pytest.mark.parametrize("drop_reverse_pulse", [False, True])
def test_the_joint_fit_is_the_dense_least_squares(drop_reverse_pulse):
    fp_true = _true_fingerprint(1)
    stretches = [_stretch(fp_true, 1, 200, 120.0, 2), _stretch(fp_true, 4 * 37 + 3, 90, 240.0, 3),
                 _stretch(fp_true, 4 * 7 + 1, 60, 60.0, 4)]
    halves = (0, 1)
    if drop_reverse_pulse:  # the reverse half never sees pulse 5: left out, the forward half alone is fitted
        keep = [~((((k >> 1) & 1) == 1) & ((k >> 2) % N == 5)) for _, k in stretches]
        stretches = [(t[m], k[m]) for (t, k), m in zip(stretches, keep)]
        halves = (0,)
    fp, var, rss, dirs, dof = fpr._joint_fit(stretches, N, QUARTER)
    fp_d, var_d, rss_d, dof_d = _dense(stretches, halves)
    assert dirs == sum(1 << h for h in halves) and dof == dof_d
    np.testing.assert_allclose(fp, fp_d, rtol=0, atol=1e-9 * np.nanmax(np.abs(fp_d)))
    np.testing.assert_allclose(var, var_d, rtol=1e-8)
    assert rss == pytest.approx(rss_d, rel=1e-8)
    assert fpr._joint_fit(stretches, N, QUARTER, cov=False)[2] == pytest.approx(rss_d, rel=1e-8)
    # and the fit finds the fingerprint it was made with (edge time noise: 2 us)
    sigma = np.sqrt(var[halves[0]::2])
    assert np.all(np.abs(fp[halves[0]::2] - fp_true[halves[0]::2]) < 5 * sigma)


def test_windows_are_placed_by_the_fingerprint_among_the_pole_pair_offsets():
    """Windows whose count starts elsewhere (each its own frame): the halls allow P/2 offsets, all
    at the same fraction; the joint fit's residual picks the true one."""
    fp_true = _true_fingerprint(5)
    ref = _stretch(fp_true, 1, 180, 120.0, 6)
    parts = [(ref, 0), (_stretch(fp_true, 4 * 20 + 1, 100, 120.0, 7), 23),
             (_stretch(fp_true, 4 * 50 + 3, 90, 240.0, 8), 41)]
    windows = []
    for (t, k), r in parts:  # the window counts from its own start: k - 4r in its frame
        windows.append(fpr.WindowEdges([(t, k - 4 * r)], (r * DELTA) % (2 * math.pi), np.zeros(1, np.int64)))
    merged = fpr.merge_windows(windows, POLES, N)
    assert merged.offsets == [0, 23, 41] and merged.dirs == 3
    ratios = [s[1] for s in merged.scores[1:]]
    assert all(x > 10 for x in ratios)  # the next offset leaves a residual many times larger
    fp, var, *_ = fpr._joint_fit([s for s, _ in parts], N, QUARTER)
    for d in (0, 1):
        np.testing.assert_allclose(merged.fp[d::2], fp[d::2] - fp[d::2].mean(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(merged.sigma, np.sqrt(var), rtol=1e-12)
    # a window of another encoder (its fingerprint matches no offset): left out, not guessed
    t, k = _stretch(_true_fingerprint(99), 4 * 9 + 1, 100, 120.0, 9)
    other = fpr.WindowEdges([(t, k - 4 * 9)], (9 * DELTA) % (2 * math.pi), np.zeros(1, np.int64))
    merged = fpr.merge_windows([*windows, other], POLES, N)
    assert merged.offsets == [0, 23, 41, None] and merged.scores[3] is not None
