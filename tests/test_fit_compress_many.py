"""The batched compression (issue 37 item 4): many motors' segments built side by side in a few
long numpy kernels (``compression.compress_many``, what ``fit_many`` compresses with) give each
motor's normal equations as the plain per-segment computation does: the design matrix of
``fit.design_matrix``, numpy's products, Cholesky.

Tolerance: the normal matrix ``R^T R`` to 1e-13 of its largest entry (the columns are the same
numbers; only the order BLAS sums the products in differs, ~1e-16), ``z`` and the floor to 1e-9
relative (a short segment's Cholesky factor amplifies that rounding by its condition). The fits of
``fit_many`` with threads equal those without, bit for bit (the same compression, in another thread).
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

from eol_cal.analysis import fit
from eol_cal.analysis.fit import compression
from eol_cal.analysis.fit.compression import compress, compress_many
from eol_cal.analysis.fit.synth import synthetic_segments

from _fit_reference import plain_normal_equations


def _reference(theta, t, y, pole_pairs, spec):
    XtX, _, z, floor, empty = plain_normal_equations(theta, t, y, pole_pairs, spec)
    return XtX, z, floor, empty


def _motors():
    """Ragged segment lengths, 3 and 4 pole pairs, with and without a current channel, segments
    longer than a piece (0.6 s: 12000 samples) and too short for the mechanical orders (0.03 s)."""
    rng = np.random.default_rng(5)
    motors = []
    for i in range(8):
        kw = dict(seg_s=(0.25, 0.6, 0.03, 0.11)[i % 4], speeds_rpm=((300.0, 600.0), (60.0, 600.0), (120.0, -240.0))[i % 3],
                  loads_a=(20.0, 65.0), pole_pairs=(3, 4)[i % 2], iq6=(1e-4, 0.3) if i % 3 == 1 else None)
        seg, _ = synthetic_segments(rng, **kw)
        cut = [len(a) - (j * 37) % 101 for j, a in enumerate(seg.theta)]
        motors.append(dataclasses.replace(
            seg, theta=[a[:c] for a, c in zip(seg.theta, cut, strict=True)], t=[a[:c] for a, c in zip(seg.t, cut, strict=True)],
            torque=[a[:c] for a, c in zip(seg.torque, cut, strict=True)],
            kt_iq=None if seg.kt_iq is None else [a[:c] for a, c in zip(seg.kt_iq, cut, strict=True)]))
    return motors


@pytest.mark.parametrize("spec", [fit.FitSpec(), fit.FitSpec(harmonics=(6, 18), drift_degree=3, mech_orders=2)])
def test_the_batched_compression_gives_each_segments_normal_equations(spec, monkeypatch):
    motors = _motors()
    monkeypatch.setattr(compression, "_GROUP", 20000)  # several groups, a piece split from its segment's others
    S = max(m.n_segments for m in motors) + 1
    batched = compress_many(motors, spec, S)
    assert len(batched) == len(motors)
    for m, c in zip(motors, batched, strict=True):
        one = compress(m, spec, S)
        for f in dataclasses.fields(c):
            np.testing.assert_array_equal(getattr(one, f.name), getattr(c, f.name))  # a motor alone: the same
        assert np.array_equal(c.R[m.n_segments:], np.tile(np.eye(spec.n_cols), (S - m.n_segments, 1, 1)))
        assert not np.any(c.n[m.n_segments:])
        assert np.any(c.cur_re) == (m.kt_iq is not None)
        for s in range(m.n_segments):
            XtX, z, floor, empty = _reference(m.theta[s], m.t[s], m.torque[s], m.pole_pairs, spec)
            RtR = c.R[s].T @ c.R[s]
            assert np.abs(RtR - XtX).max() <= 1e-13 * np.abs(XtX).max()
            np.testing.assert_allclose(c.z[s], z, rtol=1e-9, atol=1e-9 * np.abs(z).max())
            assert abs(c.floor[s] - floor) <= 1e-9 * c.sst[s]
            assert c.n[s] == len(m.theta[s]) and c.n_nuis[s] == spec.n_nuis - empty.sum()
    # a segment too short for the mechanical orders has them pinned, as alone
    short = batched[2]
    assert short.n_nuis[0] == spec.n_nuis - 2 * spec.n_mech


def test_fits_with_compression_threads_equal_those_without():
    rng = np.random.default_rng(9)
    motors = [synthetic_segments(rng, seg_s=0.05, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0))[0] for _ in range(40)]
    spec = fit.FitSpec()
    inline = fit.fit_many(motors, spec, mode="map", chunk=20, threads=0)
    assert fit.batch.compression_threads(len(motors)) == (1 if len(os.sched_getaffinity(0)) >= 2 else 0)
    threaded = fit.fit_many(motors, spec, mode="map", chunk=20)  # the default: a worker beside this thread
    for a, b in zip(inline, threaded, strict=True):
        assert a.harmonics[6]["k"].value == b.harmonics[6]["k"].value and a.delay_s == b.delay_s
        assert np.array_equal(a.coef, b.coef) and a.converged


def test_exp_i_is_numpys_complex_exponential_within_an_ulp():
    """The compression's exp(i x) (a table and the rest's series) against numpy's (glibc's sincos):
    within 2.5e-16 over angles up to 8e5 rad, negative ones, and the table's own steps."""
    from eol_cal.numerics.expi import exp_i

    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-1, 1, 5000), rng.uniform(-8e5, 8e5, 5000), np.arange(-2048, 2048) * (np.pi / 512),
                        np.arange(-2048, 2048) * (np.pi / 512) + np.pi / 1024])
    out, work = np.empty(len(x), dtype=complex), np.empty((3, len(x)), dtype=complex)
    assert np.abs(exp_i(x, out, *work) - np.exp(1j * x)).max() <= 2.5e-16


def test_design_columns_are_the_plain_trigonometric_and_legendre_functions():
    """design_matrix's columns against np.cos/np.sin of each order and numpy's Legendre polynomials
    (the powers of one exp(i theta_m) drift by ~1e-14 at the 18th harmonic of 4 pole pairs)."""
    rng = np.random.default_rng(4)
    seg, _ = synthetic_segments(rng, seg_s=0.25, speeds_rpm=(600.0, 900.0), loads_a=(20.0, 65.0), pole_pairs=4)
    spec = fit.FitSpec()
    theta, t = seg.theta[1], seg.t[1]
    X = fit.design_matrix(theta, t, seg.pole_pairs, spec)
    tn = 2.0 * (t - t[0]) / (t[-1] - t[0]) - 1.0
    legendre = np.polynomial.legendre.legvander(tn, spec.drift_degree)
    mech = [f(j * theta / seg.pole_pairs) for j in range(1, spec.n_mech + 1) for f in (np.cos, np.sin)]
    harm = [f(h * theta) for h in spec.harmonics for f in (np.sin, np.cos)]
    np.testing.assert_allclose(X, np.column_stack([legendre, *mech, *harm]), rtol=0, atol=1e-12)


def test_the_compression_threads_share_a_shared_compression_scope(monkeypatch):
    """Within ``shared_compression`` the workers' compressions are the scope's: a segment the batch
    compressed in a worker is not compressed again in this thread."""
    rng = np.random.default_rng(10)
    motors = [synthetic_segments(rng, seg_s=0.05, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0))[0] for _ in range(4)]
    spec = fit.FitSpec()
    calls = []
    real = compression.mech_span
    monkeypatch.setattr(compression, "mech_span", lambda *a, **kw: calls.append(1) or real(*a, **kw))
    with compression.shared_compression():
        fit.fit_many(motors, spec, mode="map", chunk=2, threads=2)
        assert len(calls) == sum(m.n_segments for m in motors)
        compress(motors[3], spec)
        assert len(calls) == sum(m.n_segments for m in motors)  # the worker's figures, shared
