"""The fit plot draws the fit's own model: bench response and transducer lag included."""

import numpy as np
import pytest

from eol_cal.analysis.fit import FitSpec, fit_many, path_gain
from eol_cal.analysis.fit.capture import motor_inputs
from eol_cal.analysis.fit.plot import fitted_ripple, plot_fit, segment_model
from eol_cal.domain.bench_mechanics import load_mechanics
from eol_cal.capture.synthetic import synthetic_capture

POINTS = [(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]


@pytest.mark.slow
def test_plotted_curve_is_the_fitted_model_with_the_bench_response(tmp_path):
    caps = [synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=i, theta_r0=0.7 * i, serial="M-1",
                              k6=0.00062, phase_k6=0.3, c6=0.004, phase_c6=1.1)
            for i, (rpm, iq) in enumerate(POINTS)]
    (mi,) = motor_inputs(caps, mechanics=load_mechanics("paper"))
    spec = FitSpec(harmonics=(6, 12))
    (fit,) = fit_many([mi.segments], spec)
    assert fit.converged
    gains = path_gain(mi.segments, spec)
    assert np.max(np.abs(gains - 1.0)) > 1e-3  # the bench response is not negligible here
    for s in range(mi.segments.n_segments):
        model, nuisance = segment_model(mi, fit, spec, s)
        theta = mi.segments.theta[s]
        # the curve at the samples' angles is the model less drift and mechanical order 1
        np.testing.assert_allclose(fitted_ripple(mi, fit, spec, s, theta), model - nuisance, rtol=0, atol=1e-9)
        # and it differs from the same curve without the bench response by more than that
        without = fitted_ripple(mi, fit, spec, s, theta, gains=np.ones_like(gains))
        assert np.max(np.abs(without - (model - nuisance))) > 1e-6
    png = tmp_path / "fit.png"
    plot_fit(png, mi, fit, spec)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
