"""The mechanical orders' amplitude and phase intervals (analysis/fit/mech_orders.order_estimate).

Issue 34: an absent order is reported with an interval that includes zero. An absent order's
amplitude is Rayleigh-distributed: amplitude +- 1.96 sigma holds zero for only 85 % of motors
(the normal approximation the fit used for every order). Drawn here from the phasor's own
distribution (the fit's covariance taken as known, or estimated with a few degrees of freedom as
the segments' jackknife estimates it), the figures are binomial, not timing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.analysis.fit.mech_orders import order_estimate, region_scale

#: 4000 draws: a 95 % coverage's binomial standard error is 0.34 %; the bounds below are ~4 of them
N = 4000


def _draws(amp: float, C: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    truth = np.array([amp * math.cos(0.7), amp * math.sin(0.7)])
    return truth + rng.multivariate_normal(np.zeros(2), C, size=N)


@pytest.mark.parametrize("C", [np.diag([1e-8, 1e-8]), np.array([[4e-8, 1e-8], [1e-8, 1e-8]])],
                         ids=["isotropic", "elongated"])
def test_an_absent_orders_interval_holds_zero_for_95_percent_of_motors(C: np.ndarray) -> None:
    held = 0
    for a, b in _draws(0.0, C, 1):
        amp, _ = order_estimate(float(a), float(b), C)
        assert amp.ci95 is not None
        held += amp.value - amp.ci95 <= 0.0
    assert 0.935 <= held / N <= 0.975


def test_the_normal_approximation_alone_held_zero_for_85_percent() -> None:
    # what the fit reported before: amplitude +- 1.96 sigma along the phasor (the reason for the rule)
    C = np.diag([1e-8, 1e-8])
    held = sum(math.hypot(a, b) <= 1.959963984540054 * 1e-4 for a, b in _draws(0.0, C, 2))
    assert 0.83 <= held / N <= 0.88


@pytest.mark.parametrize("sigmas", [1.0, 2.0, 3.0, 5.0, 20.0])
def test_the_amplitude_interval_covers_95_percent_or_more_at_any_amplitude(sigmas: float) -> None:
    C = np.array([[2e-8, 0.5e-8], [0.5e-8, 1e-8]])
    amp_true = sigmas * 1e-4
    covered = 0
    for a, b in _draws(amp_true, C, 3):
        amp, _ = order_estimate(float(a), float(b), C)
        assert amp.ci95 is not None
        covered += abs(amp.value - amp_true) <= amp.ci95
    assert covered / N >= 0.935


def test_a_resolved_order_keeps_the_normal_intervals() -> None:
    C = np.diag([1e-8, 4e-8])
    amp, phase = order_estimate(3e-3, 0.0, C)  # 30 sigma along the cosine axis
    assert amp.value == pytest.approx(3e-3)
    assert amp.ci95 == pytest.approx(1.959963984540054 * 1e-4)
    assert phase.value == pytest.approx(0.0)
    assert phase.ci95 == pytest.approx(1.959963984540054 * 2e-4 / 3e-3)


def test_an_unresolved_order_has_no_phase_bound() -> None:
    amp, phase = order_estimate(1e-5, 1e-5, np.diag([1e-8, 1e-8]))
    assert phase.ci95 == pytest.approx(math.pi)
    assert amp.ci95 == pytest.approx(math.sqrt(-2 * math.log(0.05)) * 1e-4)


def _estimated(C: np.ndarray, dof: int, rng: np.random.Generator) -> np.ndarray:
    """``C`` estimated from ``dof`` independent draws (Wishart / dof), scaled by ``(t(dof) / 1.96)^2``
    as the fit reports it for the one-dimensional intervals (motor_fit.wider_per_quantity)."""
    from scipy.special import stdtrit

    x = rng.multivariate_normal(np.zeros(2), C, size=dof)
    return (x.T @ x) / dof * (float(stdtrit(dof, 0.975)) / 1.959963984540054) ** 2



@pytest.mark.parametrize("dof", [7, 9])
def test_an_absent_orders_region_holds_zero_for_95_percent_with_an_estimated_covariance(dof: int) -> None:
    # the delete-one-segment jackknife of 8 segments: 7 degrees of freedom. Chi-square's 5.99 scaled by
    # the one-dimensional t (the rule before) left the origin out of the region for ~9 % (7) / ~8 % (9)
    rng = np.random.default_rng(4)
    C = np.array([[4e-8, 1e-8], [1e-8, 1e-8]])
    held = old = 0
    for a, b in _draws(0.0, C, 5):
        Ch = _estimated(C, dof, rng)
        held += order_estimate(float(a), float(b), Ch, dof)[1].ci95 == math.pi  # no phase bound: not resolved
        old += order_estimate(float(a), float(b), Ch)[1].ci95 == math.pi
    assert 0.935 <= held / N <= 0.965
    assert old / N < 0.935


@pytest.mark.parametrize("C", [np.diag([1e-8, 1e-8]), np.array([[4e-8, 1e-8], [1e-8, 1e-8]])],
                         ids=["isotropic", "elongated"])
def test_the_scatters_narrow_direction_does_not_narrow_an_absent_orders_region(C: np.ndarray) -> None:
    # the noise's covariance right (C), the segments' scatter an estimate of the same C from 8 segments:
    # where its trace was the larger, the whole scatter (the electrical quantities' rule) took its narrow
    # direction too, and the region held zero for 93.3 / 93.8 %; the noise plus the excess, per direction
    from eol_cal.analysis.fit.mech_orders import pair_covariance

    rng = np.random.default_rng(7)
    S = 8
    held = 0
    for a, b in _draws(0.0, C, 6):
        x = rng.multivariate_normal(np.zeros(2), C, size=S - 1)
        Cp, dof = pair_covariance(C, x.T @ x / (S - 1), S)
        amp, phase = order_estimate(float(a), float(b), Cp, dof)
        if phase.ci95 == math.pi:  # not resolved: the amplitude's interval reaches zero
            assert amp.ci95 is not None and amp.value <= amp.ci95
            held += 1
    assert 0.945 <= held / N <= 0.975


def test_the_pair_covariance_is_at_least_the_noise_and_the_scatter_in_every_direction() -> None:
    from eol_cal.analysis.fit.mech_orders import pair_covariance

    noise = np.diag([1.0, 1.0]) * 1e-8
    scatter = np.diag([3.0, 0.2]) * 1e-8  # trace the larger, narrower than the noise along the second axis
    C, dof = pair_covariance(noise, scatter, 8)
    for M in (noise, scatter):
        assert np.linalg.eigvalsh(C - M).min() >= -1e-20
    assert C[1, 1] >= noise[1, 1] and 7 < dof < math.inf
    same, dof_n = pair_covariance(scatter * 0.1, scatter * 0.05, 8)  # the noise wider everywhere: it alone
    assert dof_n == math.inf and np.array_equal(same, scatter * 0.1)


def test_the_region_is_chi_square_without_estimation_and_hotellings_with() -> None:
    assert region_scale(math.inf) == pytest.approx(-2 * math.log(0.05))
    # 2 nu / (nu - 1) F(2, nu - 1; 0.95) over (t(nu) / 1.96)^2: nu = 7 -> 12.0 / 1.456
    from scipy.stats import f, t

    for nu in (4.5, 7.0, 30.0):
        t2 = 2 * nu / (nu - 1) * f.ppf(0.95, 2, nu - 1)
        assert region_scale(nu) == pytest.approx(t2 * (1.959963984540054 / t.ppf(0.975, nu)) ** 2, rel=1e-9)
    assert region_scale(1e7) == pytest.approx(-2 * math.log(0.05), rel=1e-5)
