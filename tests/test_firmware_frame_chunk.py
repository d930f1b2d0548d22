"""The firmware frame's estimator run in longer compiled calls for long captures (issue 37 item 2),
and as one XLA loop kernel (issue 37 item 6, the station's process): the same estimator output bit
for bit, so the same frame offset, whatever the chunk and the loop's compilation."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

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


_SCAN = textwrap.dedent("""
    import hashlib, sys
    if sys.argv[1] == "kernel":
        from eol_cal.numerics.xla import configure_xla
        assert configure_xla()  # before the process's first JAX computation, as `eol-cal run` and `station` do
    import numpy as np
    from eol_cal.analysis.firmware_angle import firmware_config
    from eol_cal.capture.synthetic import synthetic_capture
    from eol_cal.firmware import estimator as est
    from eol_cal.firmware.options import parse_options

    # windows of a station's capture: both directions, three speeds, lengths apart (padded lanes)
    caps = [synthetic_capture(rpm=rpm, seconds=s, seed=i)
            for i, (rpm, s) in enumerate([(60.0, 0.5), (120.0, 0.3), (-60.0, 0.4), (240.0, 0.2), (-120.0, 0.25)])]
    signals = [tuple(np.asarray(c[name]) for name in ("enc_a", "enc_b", "hall")) for c in caps]
    tables = [None, (0.6, 1.6, 2.7, 3.7, 4.8, 5.8), None, (0.5, 1.5, 2.6, 3.6, 4.7, 5.8), None]
    digest = hashlib.sha256()
    for options in (0, parse_options("best")):
        for out in est.run_jax_batch(firmware_config(caps[0], options), signals, tables, chunk=est.JAX_CHUNK):
            for field in out:
                digest.update(np.ascontiguousarray(np.asarray(field)).tobytes())
    print(digest.hexdigest())
""")


def _scan_digest(loops: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", _SCAN, loops], env=env, capture_output=True, text=True, timeout=600,
                         check=True)
    return out.stdout.strip().splitlines()[-1]


@pytest.mark.slow  # two processes that compile the estimator's scan (~10 s)
def test_the_estimator_scan_as_one_loop_kernel_is_the_scan_bit_for_bit():
    # `eol-cal run` and `station` switch XLA's one-kernel loops on (numerics.xla.configure_xla): the
    # frame's scan after the last window then costs a tenth of the CPU. Its every output, both
    # estimators, per-lane hall tables and padded lanes: the same bytes as with XLA's defaults
    assert _scan_digest("kernel") == _scan_digest("default")
