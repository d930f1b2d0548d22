"""The blocked compression equals the whole-segment normal equations (fit.compress_segment)."""

import numpy as np

from eol_cal.analysis import fit
from eol_cal.analysis.fit import compression
from eol_cal.analysis.fit.synth import synthetic_segments

from _fit_reference import plain_normal_equations


def _reference(theta, t, y, pole_pairs, spec):
    _, L, z, floor, _ = plain_normal_equations(theta, t, y, pole_pairs, spec)
    return L.T, z, floor


def test_blocks_match_whole_segment(monkeypatch):
    rng = np.random.default_rng(11)
    seg, _ = synthetic_segments(rng, seg_s=0.6, speeds_rpm=(60.0, 600.0), loads_a=(20.0, 65.0))
    spec = fit.FitSpec()
    # 0.6 s at 20 kHz = 12000 samples: two blocks at the default size, 13 at 937 (a ragged last one)
    for block in (compression._BLOCK, 937):
        monkeypatch.setattr(compression, "_BLOCK", block)
        for s in range(seg.n_segments):
            th, t, y = seg.theta[s], seg.t[s], seg.torque[s]
            assert len(th) > block
            R, z, floor, *_ = fit.compress_segment(th, t, y, seg.pole_pairs, spec)
            R0, z0, floor0 = _reference(th, t, y, seg.pole_pairs, spec)
            np.testing.assert_allclose(R, R0, rtol=1e-10, atol=1e-9 * np.abs(R0).max())
            np.testing.assert_allclose(z, z0, rtol=1e-8, atol=1e-9 * np.abs(z0).max())
            assert abs(floor - floor0) <= 1e-8 * (y - y.mean()) @ (y - y.mean())


def test_short_segment_pins_mechanical_pair():
    rng = np.random.default_rng(12)
    seg, _ = synthetic_segments(rng, seg_s=0.03, speeds_rpm=(60.0, 120.0), loads_a=(20.0, 65.0))
    spec = fit.FitSpec()
    R, z, floor, sst, ymean, n, n_nuis = fit.compress_segment(seg.theta[0], seg.t[0], seg.torque[0], seg.pole_pairs, spec)
    q = spec.n_nuis
    # less than one mechanical revolution: the pairs are pinned (unit diagonal, no coupling)
    nm = 2 * spec.n_mech
    np.testing.assert_array_equal(np.diag(R)[q - nm : q], np.ones(nm))
    assert n_nuis == q - nm and n == len(seg.theta[0])
