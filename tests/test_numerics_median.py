"""eol_cal.numerics.median: bit for bit np.median (the refit's edges, stretches and hall orders read it)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.numerics.median import median


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 8, 999, 1000, 7001])
def test_median_is_np_median_bit_for_bit(n):
    rng = np.random.default_rng(n)
    for x in (rng.normal(size=n), rng.integers(-3, 4, size=n).astype(float), np.full(n, -0.0),
              np.cumsum(rng.exponential(1e-4, size=n)) * 1e3):
        got, want = median(x), float(np.median(x))
        assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want)


def test_median_of_nan_and_slices():
    x = np.arange(10.0)
    x[3] = np.nan
    assert math.isnan(median(x)) and math.isnan(float(np.median(x)))
    y = np.arange(20.0)[::3]  # a strided view, as the refit's slices
    assert median(y) == float(np.median(y))
    assert median(np.zeros(0)) != median(np.zeros(0))  # NaN, as np.median
