"""The firmware frame's estimator run in longer compiled calls for long captures (issue 37 item 2):
the same estimator output bit for bit, so the same frame offset, whatever the chunk."""

from __future__ import annotations

import numpy as np

from eol_cal.analysis.angle import capture_angle
from eol_cal.analysis.firmware_angle import LONG_CHUNK, firmware_config, firmware_frame_parts, scan_chunk
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.firmware import estimator as est


def test_scan_chunk_is_the_long_one_from_its_length_on():
    assert scan_chunk(LONG_CHUNK - 1) == est.JAX_CHUNK < LONG_CHUNK == scan_chunk(LONG_CHUNK) == scan_chunk(172_000)


def test_the_estimator_in_long_chunks_is_the_estimator_in_short_ones_bit_for_bit():
    caps = [synthetic_capture(rpm=rpm, seconds=s, seed=i) for i, (rpm, s) in enumerate([(120.0, 0.9), (-240.0, 0.5)])]
    cfg = firmware_config(caps[0])
    signals = [tuple(np.asarray(c[name]) for name in ("enc_a", "enc_b", "hall")) for c in caps]
    assert max(len(s[0]) for s in signals) >= LONG_CHUNK
    short = est.run_jax_batch(cfg, signals, chunk=est.JAX_CHUNK)
    long = est.run_jax_batch(cfg, signals, chunk=scan_chunk(max(len(s[0]) for s in signals)))
    for a, b in zip(short, long, strict=True):
        for field in est.EstimatorOut._fields:
            assert np.array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field))), field
    # and the frame's parts the fit reads: the same sums over the segments' samples
    n = len(caps[0].t)
    theta = capture_angle(caps[0]).theta_r
    (parts,) = firmware_frame_parts([(caps[0], theta, [(2000, n - 1000)], None, 0)])
    ok = (np.asarray(short[0].status) & (est.ST_NO_ANCHOR | est.ST_STANDSTILL | est.ST_NO_SPEED)) == 0
    sel = np.flatnonzero(ok[2000:n - 1000]) + 2000
    d = np.asarray(short[0].theta_hat, float)[sel] - theta[sel]
    assert parts == [(complex(np.exp(1j * d).sum()), len(sel))]
