"""The fingerprint's joint fit (each stretch's motion projected out, normal equations summed per
pulse, windows moved by moving their sums) against the dense least squares over every edge: the
same edge errors, variances, residual and degrees of freedom; and window placement over the
pole-pair offsets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.analysis import fingerprint as fpr
from eol_cal.analysis.fingerprint_fit import POLY_DEGREE, EdgeSums, PlacedWindows, joint_fit, low_order_complement
from eol_cal.firmware.mech_params import FP_FORWARD

N, POLES = 64, 8
QUARTER = POLES * math.pi / N / 4.0
DELTA = 4 * QUARTER


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
    P = low_order_complement(N)
    nF = P.shape[1]
    deg1 = POLY_DEGREE + 1
    nb = deg1 * len(stretches)
    col = {d: nb + i * nF for i, d in enumerate(dirs)}
    rows, rhs = [], []
    for g, (times, k) in enumerate(stretches):
        keep = np.isin((k >> 1) & 1, dirs)  # a half left out: its edges are not in the fit
        times, k = times[keep], k[keep]
        half = (k >> 1) & 1
        x = (times - times[0]) / (times[-1] - times[0]) * 2.0 - 1.0
        A = np.zeros((len(times), nb + nF * len(dirs)))
        A[:, g * deg1:(g + 1) * deg1] = np.polynomial.legendre.legvander(x, POLY_DEGREE)
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
    fp, var, rss, dirs, dof = joint_fit(stretches, N, QUARTER)
    assert dirs == FP_FORWARD | (FP_FORWARD << 1)
    fp_d, var_d, rss_d, dof_d = _dense(stretches, [0, 1])
    assert dof == dof_d
    np.testing.assert_allclose(fp, fp_d, rtol=0, atol=1e-9)
    np.testing.assert_allclose(var, var_d, rtol=1e-6)
    assert rss == pytest.approx(rss_d, rel=1e-6)
    # and it finds the errors: the true ones less their orders 0..2, which the fit cannot see
    P = low_order_complement(N)
    for d in (0, 1):
        seen = P @ (P.T @ fp_true[d::2])
        assert np.max(np.abs(fp[d::2] - seen)) < 2e-4
    # a placement trial needs only the residual
    fp2, var2, rss2, _, _ = joint_fit(stretches, N, QUARTER, cov=False)
    np.testing.assert_array_equal(fp2, fp)
    assert np.isnan(var2).all() and rss2 == rss


def _true_fingerprint(seed: int) -> np.ndarray:
    """(2N,) edge errors (rad electrical) without mechanical orders 0..2 in either half."""
    P = low_order_complement(N)
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


@pytest.mark.parametrize("drop_reverse_pulse", [False, True])
def test_the_joint_fit_of_one_half_or_both_is_the_dense_least_squares(drop_reverse_pulse):
    fp_true = _true_fingerprint(1)
    stretches = [_stretch(fp_true, 1, 200, 120.0, 2), _stretch(fp_true, 4 * 37 + 3, 90, 240.0, 3),
                 _stretch(fp_true, 4 * 7 + 1, 60, 60.0, 4)]
    halves = (0, 1)
    if drop_reverse_pulse:  # the reverse half never sees pulse 5: left out, the forward half alone is fitted
        keep = [~((((k >> 1) & 1) == 1) & ((k >> 2) % N == 5)) for _, k in stretches]
        stretches = [(t[m], k[m]) for (t, k), m in zip(stretches, keep, strict=True)]
        halves = (0,)
    fp, var, rss, dirs, dof = joint_fit(stretches, N, QUARTER)
    fp_d, var_d, rss_d, dof_d = _dense(stretches, list(halves))
    assert dirs == sum(1 << h for h in halves) and dof == dof_d
    np.testing.assert_allclose(fp, fp_d, rtol=0, atol=1e-9 * np.nanmax(np.abs(fp_d)))
    np.testing.assert_allclose(var, var_d, rtol=1e-8)
    assert rss == pytest.approx(rss_d, rel=1e-8)
    assert joint_fit(stretches, N, QUARTER, cov=False)[2] == pytest.approx(rss_d, rel=1e-8)
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
    fp, var, *_ = joint_fit([s for s, _ in parts], N, QUARTER)
    for d in (0, 1):
        np.testing.assert_allclose(merged.fp[d::2], fp[d::2] - fp[d::2].mean(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(merged.sigma, np.sqrt(var), rtol=1e-12)
    # a window of another encoder (its fingerprint matches no offset): left out, not guessed
    t, k = _stretch(_true_fingerprint(99), 4 * 9 + 1, 100, 120.0, 9)
    other = fpr.WindowEdges([(t, k - 4 * 9)], (9 * DELTA) % (2 * math.pi), np.zeros(1, np.int64))
    merged = fpr.merge_windows([*windows, other], POLES, N)
    assert merged.offsets == [0, 23, 41, None] and merged.scores[3] is not None


@pytest.mark.parametrize("one_half", [False, True])
def test_the_fingerprints_standard_errors_solved_when_asked_are_the_fits_own(one_half):
    """merge_windows fits without the variances; ``sigma``, solved from the fit's normal equations
    when first read, is the joint fit's with them (``cov=True``) bit for bit, inf where a half
    was not measured."""
    fp_true = _true_fingerprint(5)
    stretches = [_stretch(fp_true, 1, 180, 120.0, 6), _stretch(fp_true, 4 * 20 + 1, 100, 120.0, 7)]
    if one_half:  # the A edges at 4m + 1 only
        stretches = [(t[(k >> 1) & 1 == 0], k[(k >> 1) & 1 == 0]) for t, k in stretches]
    merged = fpr.merge_windows([fpr.WindowEdges(stretches, 0.0, np.zeros(1, np.int64))], POLES, N)
    placed = PlacedWindows(N)
    placed.add(EdgeSums(stretches, N, QUARTER), 0)
    _, var, _, dirs, _ = placed.fit(cov=True)
    want = np.sqrt(np.where(np.isfinite(var), np.maximum(var, 0.0), np.inf))
    for d in (0, 1):
        if not dirs & (1 << d):
            want[d::2] = np.inf
    assert merged.dirs == dirs == (1 if one_half else 3)
    assert "sigma" not in vars(merged)  # not solved until read
    np.testing.assert_array_equal(merged.sigma, want)
    assert np.isinf(merged.sigma).any() == one_half


def test_a_placements_trials_in_one_pass_are_each_trial_alone_bit_for_bit():
    """:meth:`PlacedWindows.trials` stacks a window's products at every offset it tries; each
    offset's normal equations, residual and degrees of freedom are those of that offset alone
    (a fresh window's sums each time, so no trial reads another's cached products)."""
    fp_true = _true_fingerprint(5)
    ref = EdgeSums([_stretch(fp_true, 1, 180, 120.0, 6)], N, QUARTER)
    stretches = [_stretch(fp_true, 4 * 20 + 1, 100, 120.0, 7), _stretch(fp_true, 4 * 50 + 3, 90, 240.0, 8)]
    placed = PlacedWindows(N)
    placed.add(ref, 0)
    shifts = [23, 0, 39, 55, 23]  # the true offset, others, a repeat
    together = placed.trials(EdgeSums(stretches, N, QUARTER), shifts)
    for shift, got in zip(shifts, together, strict=True):
        (alone,) = placed.trials(EdgeSums(stretches, N, QUARTER), [shift])
        assert got == alone and got is not None
        w = EdgeSums(stretches, N, QUARTER)
        for a, b in zip(w.normals((0, 1), [7, shift])[1], _normal_alone(w, shift), strict=True):
            np.testing.assert_array_equal(a, b)


def _normal_alone(w: EdgeSums, shift: int) -> tuple:
    """A window's normal equations at one offset by two-dimensional products (the code before
    the trials were stacked): the reference the stacked products must equal bit for bit."""
    per_half, ss, n = w.part((0, 1))
    P = low_order_complement(N)
    nF = P.shape[1]
    G, rhs, Ts = np.zeros((2 * nF, 2 * nF)), np.zeros(2 * nF), []
    for i, (J, counts, r, S) in enumerate(per_half):
        PJ = P[(J + shift) % N]
        s = slice(i * nF, (i + 1) * nF)
        G[s, s] = PJ.T @ (counts[:, None] * PJ)
        rhs[s] = -PJ.T @ r
        Ts.append(PJ.T @ S)
    T = np.concatenate(Ts)
    return G - T @ T.T, rhs, ss, n


def _counts_int64(enc_a, enc_b):
    """quadrature_counts and a_edges as they were written, in int64 throughout (the reference)."""
    from eol_cal.firmware.estimator import quadrature_phase

    ph = np.asarray(quadrature_phase(np.asarray(enc_a).astype(np.int64) & 1, np.asarray(enc_b).astype(np.int64) & 1))
    d = np.diff(ph) % 4
    step = np.concatenate(([0], np.where(d == 1, 1, np.where(d == 3, -1, 0))))
    return ph[0] + np.cumsum(step), step, int(np.sum(d == 2))


@pytest.mark.parametrize("dtype", [np.int8, np.uint8, np.int64, float, bool])
def test_the_quadrature_count_in_the_levels_own_integers_is_the_int64_one(dtype):
    rng = np.random.default_rng(7)
    for _ in range(40):
        n = int(rng.integers(2, 2000))
        # mostly single steps, some double ones and repeats
        a, b = (rng.integers(0, 2, n).astype(dtype) for _ in range(2))
        t = np.cumsum(rng.uniform(1e-4, 2e-4, n))
        q, step, qep = fpr.quadrature_counts(a, b)
        q0, step0, qep0 = _counts_int64(a, b)
        assert qep == qep0 and q.dtype == step.dtype == np.int64
        assert np.array_equal(q, q0) and np.array_equal(step, step0)
        a_int = np.asarray(a).astype(np.int64) & 1
        idx = np.flatnonzero(np.concatenate(([False], a_int[1:] != a_int[:-1])) & (step0 != 0))
        times, k, dirn = fpr.a_edges(t, a, b, q, step)
        assert np.array_equal(times, 0.5 * (t[idx - 1] + t[idx]))
        assert np.array_equal(k, np.where(step0[idx] > 0, q0[idx], q0[idx] + 1))
        assert np.array_equal(dirn, np.where(step0[idx] > 0, 1, -1))
