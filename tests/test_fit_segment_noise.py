"""The noise at the harmonics (analysis/fit/segment_noise.py) measured for less work, with the same
numbers (issue 37 item 2): the bins' exponentials in whole rows, the 6th alone where only the model
check reads it, and no measurement at all where the intervals keep the white noise."""

from __future__ import annotations

import math

import numpy as np

from eol_cal.analysis.fit import FitSpec, fit_segments
from eol_cal.analysis.fit.model import bin_steps, noise_bins
from eol_cal.analysis.fit.motor_fit import MIN_SEGMENTS_SCATTER, at_line_noise, takes_line_noise
from eol_cal.analysis.fit.segment_noise import segment_noise
from eol_cal.analysis.fit.synth import synthetic_segments


def _path(omega):
    w0, zeta = 2 * math.pi * 250.0, 0.1
    r = np.abs(np.asarray(omega, dtype=float)) / w0
    g = 1.0 / (1.0 - r * r + 2j * zeta * r)
    return np.where(np.asarray(omega) < 0, np.conj(g), g)


def test_bin_steps_are_the_bins_exponentials_as_the_powers_spelled_them():
    b = 2 * math.pi * np.linspace(0.0, 1.0, 1237)
    k = noise_bins()
    steps = bin_steps(b, k)
    # the construction before (every bin's column gathered from the powers and conjugated in place)
    step = np.exp(-1j * b)
    powers = np.empty((10, len(b)), dtype=complex)
    powers[0] = 1.0
    for j in range(1, 10):
        powers[j] = powers[j - 1] * step
    ki = k.astype(int)
    before = np.where(ki[None, :] > 0, powers[np.abs(ki)].T, np.conj(powers[np.abs(ki)].T))
    assert steps.shape == (len(b), len(k)) and np.array_equal(steps, before)
    assert np.allclose(steps, np.exp(-1j * np.outer(b, k)), rtol=0.0, atol=1e-12)


def test_the_6th_alone_is_the_6th_of_every_harmonic():
    # with the ECU's current (iq6) and a bench response: every branch of line_noise
    seg, _ = synthetic_segments(np.random.default_rng(5), speeds_rpm=(300.0, 600.0), loads_a=(20.0, 60.0),
                                seg_s=0.1, noise_nm=0.005, iq6=(0.02, 0.3), path_response=_path)
    assert seg.kt_iq is not None
    spec = FitSpec()
    every = segment_noise(seg, spec, 1.5e-4)
    sixth = segment_noise(seg, spec, 1.5e-4, harmonics=(6,))
    assert every.harmonics == (6, 12, 18) and sixth.harmonics == (6,)
    assert np.array_equal(sixth.var_pair[:, 0], every.var_pair[:, 0])
    assert np.array_equal(sixth.dof[:, 0], every.dof[:, 0])
    assert np.array_equal(sixth.var_white, every.var_white) and np.array_equal(sixth.n, every.n)
    idx = np.arange(seg.n_segments)
    assert sixth.ratio(idx) == every.ratio(idx)


def test_the_noise_is_measured_for_the_intervals_only_where_they_take_it():
    spec = FitSpec()
    few, _ = synthetic_segments(np.random.default_rng(1), speeds_rpm=(300.0, 600.0), loads_a=(20.0, 60.0),
                                seg_s=0.1, noise_nm=0.005)
    many, _ = synthetic_segments(np.random.default_rng(1), speeds_rpm=(300.0, 600.0), loads_a=(20.0, 60.0),
                                 directions=(1, -1), seg_s=0.1, noise_nm=0.005)
    assert few.n_segments < MIN_SEGMENTS_SCATTER <= many.n_segments
    fit_few, fit_many = fit_segments(few, spec), fit_segments(many, spec)
    assert fit_few.converged and fit_many.converged
    assert not takes_line_noise(fit_few) and takes_line_noise(fit_many)
    # where it does not, the intervals stay the white noise's whatever the noise measured
    row_var = segment_noise(few, spec, fit_few.delay_s).row_variance()
    assert at_line_noise(fit_few, spec, row_var) is fit_few
    moved = at_line_noise(fit_many, spec, segment_noise(many, spec, fit_many.delay_s).row_variance())
    assert moved.harmonics[6]["k"].ci95 != fit_many.harmonics[6]["k"].ci95


def test_the_orders_noise_shares_its_segments_bins_with_the_same_values():
    # mech_orders.order_noise builds the segment's bins once for its orders: each order's figure is
    # line_noise's with the bins built for that order alone (the code before), bit for bit
    from eol_cal.analysis.fit.mech_orders import NOISE_GAP, ORDERS, order_noise
    from eol_cal.analysis.fit.model import line_noise

    rng = np.random.default_rng(3)
    t = np.arange(6000) / 20000.0
    w_m = 2 * math.pi * 2.0  # 120 rpm
    th_m = w_m * t + 0.002 * np.sin(2 * math.pi * 37.0 * t)
    res, cur = rng.normal(0.0, 0.01, len(t)), rng.normal(0.0, 0.004, len(t))
    spec = FitSpec()
    got = order_noise(res, cur, th_m, t, w_m, spec, 1.5e-4, _path, pole_pairs=3)
    n, T, k = len(t), float(t[-1] - t[0]), noise_bins()
    lines = np.concatenate([[0.0], np.outer(list(ORDERS) + [h * 3 for h in spec.harmonics], [w_m, -w_m]).ravel()])
    for i, h in enumerate(ORDERS):
        omega = h * w_m + 2 * math.pi * k / T
        ok = np.min(np.abs(omega[:, None] - lines[None, :]), axis=1) >= 2 * math.pi * NOISE_GAP / T
        assert ok.any()
        alone = line_noise(res, cur, h * (th_m - th_m[0]), 2 * math.pi * (t - t[0]) / T, k[ok], omega[ok], spec,
                           1.5e-4, _path) * n / 2.0
        assert got[i] == alone


def _noise_by_definition(seg, spec, tau_s, h):
    """The 6th's (or ``h``'s) var_pair of every segment as line_noise's docstring defines it: the
    residual of an orthonormal basis (QR) of the segment's columns, each bin's phasor summed from its
    own complex exponentials, the current's through the path and the transducer, each bin's power
    over the share of it the fit left."""
    from eol_cal.analysis.fit.model import design_matrix, transducer_gain
    from eol_cal.analysis.fit.segment_noise import _clear_bins

    out = []
    for s in range(seg.n_segments):
        theta, t = np.asarray(seg.theta[s]), np.asarray(seg.t[s])
        A = design_matrix(theta, t, seg.pole_pairs, spec)
        Q, _ = np.linalg.qr(A[:, np.any(A != 0.0, axis=0)])
        Y = np.column_stack([seg.torque[s]] + ([] if seg.kt_iq is None else [seg.kt_iq[s]]))
        res = Y - Q @ (Q.T @ Y)
        n, T = len(t), float(t[-1] - t[0])
        k = noise_bins()[_clear_bins(noise_bins(), h * float(seg.omega_e[s]) / (2 * math.pi) * T, spec.drift_degree)]
        E = np.exp(-1j * (h * (theta - theta[0]))[:, None] - 1j * (2 * math.pi * (t - t[0]) / T)[:, None] * k[None, :])
        X = 2.0 / n * (res.T @ E)
        e = X[0]
        if seg.kt_iq is not None:
            omega = h * float(seg.omega_e[s]) + 2 * math.pi * k / T
            e = e - transducer_gain(spec, tau_s, omega) * np.asarray(seg.path_response(omega)) * X[1]
        left = 1.0 - np.sum(np.abs(Q.T @ E) ** 2, axis=0) / n
        out.append(float(np.mean(np.abs(e) ** 2 / np.maximum(left, 0.1))) / 2.0)
    return np.array(out)


def test_the_noise_is_its_definition_within_rounding():
    # segment_noise reads each bin's sums from the normal equations (no orthonormal basis of the
    # samples, issue 37): the figures as defined, within 1e-9 relative (their differences: ~1e-11)
    for seed, kw in ((2, dict(iq6=(0.02, 0.3), path_response=_path)), (4, {})):
        seg, _ = synthetic_segments(np.random.default_rng(seed), speeds_rpm=(60.0, 300.0, 600.0), loads_a=(20.0, 60.0),
                                    directions=(1, -1), seg_s=0.1, noise_nm=0.005, **kw)
        spec = FitSpec()
        got = segment_noise(seg, spec, 1.5e-4)
        for j, h in enumerate(spec.harmonics):
            want = _noise_by_definition(seg, spec, 1.5e-4, h)
            assert np.allclose(got.var_pair[:, j], want, rtol=1e-9, atol=0.0)


def _exp_numpy(x):
    return np.exp(-1j * x)


def _exp_table(x):
    from eol_cal.numerics.expi import exp_i

    work = np.empty((4, len(x)), dtype=complex)
    return exp_i(-x, work[0], work[1], work[2], work[3])


def _per_segment(seg, spec, tau_s, harmonics, expo):
    """segment_noise as it was built segment by segment (before noise_pass, issue 37 item 2): each
    segment's columns, normal matrix, bins and turn on its own arrays; ``expo(x)``: exp(-i x), numpy's
    (the code before) or the table's (:func:`~eol_cal.numerics.expi.exp_i`, noise_pass')."""
    from eol_cal.analysis.fit.model import bins_noise, design_matrix_t
    from eol_cal.analysis.fit.segment_noise import _clear_bins, _fitted
    from eol_cal.numerics.gemm import gram_halves

    bins = noise_bins()
    var_pair, var_white = np.zeros((seg.n_segments, len(harmonics))), np.zeros(seg.n_segments)
    for s in range(seg.n_segments):
        theta, t = np.asarray(seg.theta[s], dtype=float), np.asarray(seg.t[s], dtype=float)
        XT = design_matrix_t(theta, t, seg.pole_pairs, spec)
        G = gram_halves(XT, [(0, XT.shape[1], len(XT))], np.zeros((1, len(XT), len(XT))))[0]
        Y = np.column_stack([seg.torque[s]] + ([] if seg.kt_iq is None else [seg.kt_iq[s]]))
        res, basis = _fitted(XT, Y, G)
        n, T = len(t), float(t[-1] - t[0])
        step = expo(2 * math.pi * (t - t[0]) / T)
        powers = np.empty((noise_bins().max().astype(int) + 1, n), dtype=complex)
        powers[0] = 1.0
        for j in range(1, len(powers)):
            powers[j] = powers[j - 1] * step
        cur = res[:, 1] if seg.kt_iq is not None else None
        for j, h in enumerate(harmonics):
            k = bins[_clear_bins(bins, h * float(seg.omega_e[s]) / (2 * math.pi) * T, spec.drift_degree)]
            ki = k.astype(int)
            w = np.where((ki > 0)[:, None], powers[np.abs(ki)], np.conj(powers[np.abs(ki)])) * expo(h * (theta - theta[0]))
            omega = h * float(seg.omega_e[s]) + 2 * math.pi * k / T
            var_pair[s, j] = bins_noise(res[:, 0], cur, np.concatenate([w.real, w.imag]), omega, spec, tau_s,
                                        seg.path_response, basis=basis)
        var_white[s] = 2.0 * float(res[:, 0] @ res[:, 0]) / max(n - XT.shape[0], 1) / n
    return var_pair, var_white


def test_one_pass_over_the_segments_is_the_per_segment_construction_bit_for_bit():
    # noise_pass builds the columns, the bins' powers and the lines' turns of every segment side by
    # side (and one BLAS call makes every normal matrix): the same figures as segment by segment with
    # the same exponentials, bit for bit; the thread's buffers, reused by a smaller motor and then a
    # larger one, change nothing. Against numpy's complex exp (the code before: glibc's per sample)
    # the table's moves the figures within 1e-13 relative (2e-15 on the refit bench's serials)
    cases = [(2, dict(iq6=(0.02, 0.3), path_response=_path), (60.0, 300.0, 600.0), 0.1),
             (4, {}, (120.0, 240.0), 0.35), (6, {}, (60.0, 300.0), 0.05)]
    for seed, kw, speeds, seg_s in cases + cases[:1]:
        seg, _ = synthetic_segments(np.random.default_rng(seed), speeds_rpm=speeds, loads_a=(20.0, 60.0),
                                    directions=(1, -1), seg_s=seg_s, noise_nm=0.005, **kw)
        spec = FitSpec()
        for harmonics in (spec.harmonics, (6,)):
            got = segment_noise(seg, spec, 1.5e-4, harmonics=harmonics)
            var_pair, var_white = _per_segment(seg, spec, 1.5e-4, harmonics, _exp_table)
            assert np.array_equal(got.var_pair, var_pair) and np.array_equal(got.var_white, var_white)
            before, white_before = _per_segment(seg, spec, 1.5e-4, harmonics, _exp_numpy)
            assert np.allclose(got.var_pair, before, rtol=1e-13, atol=0.0)
            assert np.array_equal(got.var_white, white_before)  # the residual is the exponentials' no part
