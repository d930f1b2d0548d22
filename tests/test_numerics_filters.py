"""The p-p figure's filters and the angle's interpolant without scipy.signal, scipy.ndimage and
scipy.interpolate (issue 37: `eol-cal fit` without a wait): the same results as scipy's, bit for bit
where the algorithm allows it (PCHIP, the Hampel filter), within a stated tolerance where the
recursion is evaluated in another order (the zero-phase Butterworth low-pass)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view
# scipy's signal, ndimage and interpolate (the references) are imported in the tests that use them:
# ~2 s of imports, not in every worker's collection

from eol_cal.analysis.metrics import hampel
from eol_cal.numerics import iir
from eol_cal.numerics.pchip import pchip, sorted_counts


@pytest.mark.parametrize("order", range(1, 9))
def test_the_sections_are_scipys_butter(order):
    from scipy.signal import butter

    for fc in (5.0, 96.0, 1920.0, 7000.0):
        assert np.allclose(iir.butter_lowpass_sos(order, fc, 20000.0), butter(order, fc, fs=20000.0, output="sos"),
                           rtol=1e-13, atol=1e-15)


def test_the_zero_phase_lowpass_is_scipys_sosfiltfilt_within_1e_10_of_the_range():
    """The ripple's cut-off is 48 x the electrical frequency: above 2e-3 x fs at every speed a
    capture holds a whole revolution at; there the difference stays under 1e-10 of the signal's
    range (measured: up to 4e-11 near 2e-3 with order 8, ~1e-14 above 5e-2; the typed fit
    goldens, p-p figures included, hold to 1e-12 relative)."""
    from scipy.signal import butter, sosfiltfilt

    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(60):
        fs = float(rng.choice([10000.0, 20000.0, 50000.0]))
        order = int(rng.integers(1, 9))
        fc = fs * 10 ** rng.uniform(np.log10(2e-3), np.log10(0.44))
        n = int(rng.integers(50, 30000))
        x = 3.0 + 0.01 * rng.normal(size=n).cumsum() + 0.05 * np.sin(0.01 * np.arange(n))
        ref = sosfiltfilt(butter(order, fc, fs=fs, output="sos"), x)
        worst = max(worst, float(np.max(np.abs(iir.lowpass_zero_phase(x, fs, fc, order) - ref)) / np.ptp(x)))
    assert worst < 1e-10


def test_a_signal_no_longer_than_the_padding_is_refused_as_by_scipy():
    from scipy.signal import sosfiltfilt

    sos = iir.butter_lowpass_sos(6, 100.0, 1000.0)
    with pytest.raises(ValueError, match="padlen, which is 21"):
        iir.sosfiltfilt(sos, np.ones(21))
    with pytest.raises(ValueError, match="padlen, which is 21"):
        sosfiltfilt(sos, np.ones(21))
    assert np.allclose(iir.sosfiltfilt(sos, np.ones(22)), 1.0)  # a constant passes unchanged


def test_pchip_and_its_derivative_are_scipys_bit_for_bit():
    from scipy.interpolate import PchipInterpolator

    rng = np.random.default_rng(0)
    for trial in range(150):
        n = int(rng.integers(2, 2000))
        x = np.cumsum(rng.uniform(1e-5, 1e-3, size=n)) + rng.uniform(-1, 1)
        y = (np.cumsum(rng.integers(-1, 3, size=n)) * 0.0123, rng.normal(size=n), np.cumsum(rng.uniform(0, 1, n)))[trial % 3]
        ref, ours = PchipInterpolator(x, y, extrapolate=False), pchip(x, y)
        xq = np.concatenate([np.linspace(x[0] - 1e-3, x[-1] + 1e-3, 3 * n), x])
        assert np.array_equal(ours(xq), ref(xq), equal_nan=True)
        assert np.array_equal(ours.derivative()(xq), ref.derivative()(xq), equal_nan=True)
    with pytest.raises(ValueError, match="strictly increasing"):
        pchip(np.array([0.0, 1.0, 1.0]), np.zeros(3))


def test_pchip_at_sorted_queries_inside_is_the_searched_evaluation_bit_for_bit():
    # the angle's path (a capture's samples between its first and last edge): each interval's run of
    # queries from a search of the knots, not a search per query; queries on the knots, both ends included
    rng = np.random.default_rng(1)
    for _ in range(100):
        n = int(rng.integers(2, 400))
        x = np.cumsum(rng.uniform(1e-5, 1e-3, size=n)) + rng.uniform(-1, 1)
        f = pchip(x, np.cumsum(rng.normal(size=n)))
        xq = np.sort(np.concatenate([rng.uniform(x[0], x[-1], int(rng.integers(0, 3000))), x[rng.integers(0, n, 5)],
                                     x[[0, -1]]]))
        assert np.array_equal(np.repeat(np.arange(n - 1), sorted_counts(x, xq)),
                              np.clip(np.searchsorted(x, xq, side="right") - 1, 0, n - 2))
        ours, ref = f.with_slope(xq, sorted_inside=True), f.with_slope(xq)
        assert np.array_equal(ours[0], ref[0]) and np.array_equal(ours[1], ref[1])


def _hampel_scipy(x, k, n_sigma=3.0):
    """The Hampel filter as it was written on scipy.ndimage's median filter (every window's median)."""
    from scipy.ndimage import median_filter

    mode = "mirror" if len(x) > k else "nearest"
    med = median_filter(x, size=2 * k + 1, mode=mode)
    d = np.abs(np.diff(x))
    step = float(d[d > 0].min()) if (d > 0).any() else 0.0
    floor = max(1.4826 * float(np.median(d)) / np.sqrt(2.0), step) if len(d) else 0.0
    win = sliding_window_view(np.pad(x, k, mode="reflect" if mode == "mirror" else "edge"), 2 * k + 1)
    mad = np.median(np.abs(win - med[:, None]), axis=1)
    bad = np.abs(x - med) > n_sigma * np.maximum(1.4826 * mad, floor)
    return np.where(bad, med, x), bad


def test_the_hampel_filter_is_the_median_filters_bit_for_bit():
    """Noisy, quantised, flat and staircase records with spikes, short and long, narrow and wide windows."""
    rng = np.random.default_rng(3)
    for trial in range(200):
        n, k = int(rng.integers(2, 4000)), int(rng.integers(1, 15))
        x = (rng.normal(size=n) * 0.01 + 2, np.round((rng.normal(size=n) * 0.01 + 2) * 300) / 300, np.full(n, 1.5),
             np.round(np.sin(np.arange(n) * 0.01) * 5) / 5)[trial % 4]
        spikes = rng.integers(0, n, max(1, n // 200))
        x[spikes] += rng.normal(size=len(spikes)) * 0.2
        y, s = hampel(x, k)
        y_ref, s_ref = _hampel_scipy(x, k)
        assert np.array_equal(y, y_ref) and np.array_equal(s, s_ref), (trial, n, k)
