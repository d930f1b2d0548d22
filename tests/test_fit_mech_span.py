"""A segment that covers a mechanical order's whole period carries the order (issue 34).

A segment is cut to whole electrical revolutions, so its samples span them less one sample's
travel: 3 electrical revolutions (one mechanical, 3 pole pairs) read 0.99995 of a revolution at
20 kHz. Counted as shorter than a period, the order was left to the drift polynomial, which
cannot follow a whole sine period, and its residual leaked into the 6th: on `mech23` plant motors
(order 1 up to 6 mN*m) a speed band's c6 moved by up to 9 % and k6 by up to 2 %, depending on
each segment's sample count; noise-free, on the plant's true angle too, and none without the
orders.
"""

import math

import numpy as np
import pytest

from eol_cal.analysis.fit import FitSpec, fit_many
from eol_cal.analysis.fit.model import mech_resolved, mech_span
from eol_cal.analysis.fit.synth import synthetic_segments


def test_a_whole_period_less_one_sample_carries_the_order_a_shorter_piece_does_not():
    spec = FitSpec()
    n, pp = 20000, 3
    theta = np.arange(n) * (2 * math.pi * pp / n)  # one mechanical revolution, sampled
    span = mech_span(theta, pp)
    assert span < 1.0
    assert mech_resolved(spec, 1, span) and mech_resolved(spec, 3, span / 3)
    assert not mech_resolved(spec, 1, 0.9) and not mech_resolved(spec, 2, 0.45)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_segments_of_one_mechanical_revolution_fit_the_6th_exactly(seed):
    # 60 rpm segments of exactly one mechanical revolution (the order-1 unbalance's whole period),
    # 120 rpm of two; noise-free: before, the 60 rpm segments lost order 1 and k6 was off by
    # 0.4-0.9 %, c6 by 0.5-5 %
    seg, truth = synthetic_segments(np.random.default_rng(seed), speeds_rpm=(60.0, 120.0), loads_a=(20.0, 65.0),
                                    seg_s=1.0, noise_nm=0.0, mech_nm=0.006, drift_nm_per_s=0.0, delay_s=2.65e-3)
    assert all(mech_span(th, seg.pole_pairs) < 1.0 for th in seg.theta[:2])
    (f,) = fit_many([seg], FitSpec(harmonics=(6,)), mode="loop")
    k, c = f.harmonics[6]["k"], f.harmonics[6]["c"]
    assert abs(k.value / truth["k6"] - 1.0) < 1e-4, 100 * (k.value / truth["k6"] - 1.0)
    assert abs(c.value / truth["c6"] - 1.0) < 1e-4, 100 * (c.value / truth["c6"] - 1.0)
    assert abs(math.remainder(c.phase - truth["phase_c6"], 2 * math.pi)) < 1e-4
