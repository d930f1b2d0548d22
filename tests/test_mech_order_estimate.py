"""The mechanical orders' amplitude and phase intervals (analysis/fit/mech_orders.order_estimate).

Issue 34: an absent order is reported with an interval that includes zero. An absent order's
amplitude is Rayleigh-distributed: amplitude +- 1.96 sigma holds zero for only 85 % of motors
(the normal approximation the fit used for every order). Drawn here from the phasor's own
distribution (the fit's covariance taken as known), the figures are binomial, not timing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.analysis.fit.mech_orders import order_estimate

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
