"""The scipy reference fit on its own (``eol_cal.analysis.fit.scipy_ref``, the plain per-sample
least squares a user would write first): a small noiseless motor, recovered. The slow test in
tests/test_fit_core.py holds the compressed JAX fit to the same optimum on a larger one."""

from __future__ import annotations

import numpy as np
import pytest

from eol_cal.analysis.fit import FitSpec
from eol_cal.analysis.fit.synth import synthetic_segments
from eol_cal.numerics.wrap import wrap_pi


def test_the_scipy_reference_recovers_a_noiseless_motor():
    # scipy.optimize: ~1 s to import, in the test, not in every worker's collection
    from eol_cal.analysis.fit.scipy_ref import fit_segments_scipy

    # no noise, drift or mechanical orders: the model is the signal, so the optimum is the truth
    seg, truth = synthetic_segments(np.random.default_rng(7), seg_s=0.01, noise_nm=0.0, drift_nm_per_s=0.0,
                                    mech_nm=0.0, speeds_rpm=(600.0, 1200.0), loads_a=(20.0, 65.0))
    ref = fit_segments_scipy(seg, FitSpec())
    assert ref["success"]
    (k6, phase_k6), (c6, phase_c6) = ref["harmonics"][6]["k"], ref["harmonics"][6]["c"]
    assert k6 == pytest.approx(truth["k6"], rel=1e-9) and abs(wrap_pi(phase_k6 - truth["phase_k6"])) < 1e-9
    assert c6 == pytest.approx(truth["c6"], rel=1e-9) and abs(wrap_pi(phase_c6 - truth["phase_c6"])) < 1e-9
    assert ref["delay_s"] == pytest.approx(truth["delay_s"], rel=1e-9)
    assert ref["cost"] < 1e-20  # nothing left but rounding (N*m^2)
