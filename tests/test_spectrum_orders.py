"""Order spectrum on known harmonic sums, and the encoder quantisation figures."""

import numpy as np
import pytest
from _analysis_motion import motion_capture

from eol_cal.analysis.angle import capture_angle
from eol_cal.numerics.wrap import wrap_pi
from eol_cal.analysis.spectrum import capture_spectrum, order_spectrum, quantisation_figures
from eol_cal.errors import InputError

FS = 20000.0
T = np.arange(0.0, 2.3, 1.0 / FS)
HARMONICS = {6: (0.05, 0.4), 12: (0.01, -1.0), 18: (0.004, 2.5), 36: (0.005, 3.0), 1: (0.002, -2.0)}
MECH1 = (0.02, 2.0)


def _torque(theta):
    x = 3.2 + MECH1[0] * np.cos(theta / 3 + MECH1[1])
    for n, (a, ph) in HARMONICS.items():
        x = x + a * np.cos(n * theta + ph)
    return x


@pytest.mark.parametrize("direction", [1, -1])
def test_known_harmonic_sum_returns_amplitudes_and_phases(direction):
    theta = direction * 3 * 2 * np.pi * T + 0.3
    s = order_spectrum(theta, _torque(theta), poles=6, t=T)
    for n, (a, ph) in HARMONICS.items():
        assert s.amplitude(n) == pytest.approx(a, rel=1e-3), n
        assert abs(wrap_pi(s.phase(n) - ph)) < 1e-3, n
    others = np.delete(s.amplitude_nm, [n - 1 for n in HARMONICS])
    assert others.max() < 1e-6
    assert s.mech1_amplitude_nm == pytest.approx(MECH1[0], rel=1e-3)
    assert abs(wrap_pi(s.mech1_phase_rad - MECH1[1])) < 1e-3
    assert s.T_avg_nm == pytest.approx(3.2, abs=1e-6)
    assert s.n_elec_revs == 6  # 2.3 s at 60 rpm: two whole mechanical revolutions


def test_contract_sine_convention_converts():
    theta = 3 * 2 * np.pi * T
    c6, phase_c6 = 0.03, 0.7
    s = order_spectrum(theta, 3.0 - c6 * np.sin(6 * theta + phase_c6), poles=6)
    assert s.amplitude(6) == pytest.approx(c6, rel=1e-3)
    assert abs(wrap_pi(s.phase(6) - np.pi / 2 - phase_c6)) < 1e-3


def test_less_than_a_mechanical_revolution_gives_electrical_orders_only():
    t = np.arange(0.0, 0.8, 1.0 / FS)
    theta = 3 * 2 * np.pi * t
    s = order_spectrum(theta, 3.0 + 0.05 * np.cos(6 * theta), poles=6)
    assert s.n_elec_revs == 2
    assert np.isnan(s.mech1_amplitude_nm)
    assert s.amplitude(6) == pytest.approx(0.05, rel=1e-3)
    with pytest.raises(InputError):
        order_spectrum(theta[:4000], np.ones(4000), poles=6)


def test_spectrum_through_the_reconstructed_angle():
    theta_m = 2 * np.pi * T + 0.3
    cap = motion_capture(T, theta_m, torque=_torque(3 * theta_m), phi_enc=0.02)
    s = capture_spectrum(cap)
    assert s.amplitude(6) == pytest.approx(0.05, rel=2e-3)
    assert abs(wrap_pi(s.phase(6) - 0.4)) < np.deg2rad(0.5)


def test_quantisation_figures_of_the_paper_encoder():
    theta_m = 2 * np.pi * T + 0.3
    cap = motion_capture(T, theta_m, torque=_torque(3 * theta_m))
    q = quantisation_figures(cap, capture_angle(cap))
    assert q.deg_per_count == pytest.approx(16.875)  # the paper's 64 PPR resolution
    assert q.deg_per_edge == pytest.approx(16.875 / 4)
    # raw angle is a sawtooth from 0 to one count: RMS = step/sqrt(3), max = step
    assert q.enc_error_rms_deg == pytest.approx(16.875 / np.sqrt(3), rel=0.01)
    assert q.enc_error_max_deg == pytest.approx(16.875, rel=0.01)
    assert q.eta_pct == pytest.approx(4.306, abs=1e-3)
