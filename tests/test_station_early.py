"""The windows worked on while the dyno turns (eol_cal.station.early): the fit that takes them gives
the result the fit of the capture file gives."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from eol_cal.analysis.fit.motors import FitOptions, fit_motors
from eol_cal.capture import read_capture
from eol_cal.dyno.profile_run import acquire
from eol_cal.dyno.setpoints import DynoSetpoint
from eol_cal.dyno.transfer import DynoConfig
from eol_cal.dyno.sim_dyno import DynoSim, DynoSimThread
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.station.early import EarlyWindows

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
SEGMENTS = [DynoSetpoint(60.0, 0.7, iq=20.0), DynoSetpoint(60.0, 0.7, iq=50.0), DynoSetpoint(-60.0, 0.7, iq=-40.0)]


def _no_times(doc):
    """The result document without what differs from run to run (creation time)."""
    return {k: v for k, v in doc.items() if k not in ("created", "tool")}


@pytest.mark.slow  # a capture and two fits: 14 s
def test_a_fit_on_the_early_windows_equals_the_fit_of_the_capture_file(tmp_path):
    options = FitOptions(batch="loop")
    early = EarlyWindows(poles=6, encoder_ppr=64, estimator_options=options.estimator_options, n_windows=len(SEGMENTS))
    with DynoSimThread(DynoSim(synthetic_source, serial="E-1", realtime=True)) as dyno:
        cap = acquire(DynoConfig(port=dyno.port), SEGMENTS, tmp_path / "cap.mf4", on_window=early.on_window)
    early.wait()
    with_early = fit_motors([cap], options, "t", prepared=early)
    early.close()
    # every window's angle and part of the firmware frame came from the work done as it arrived
    assert early.used == early.frames_used == len(SEGMENTS)
    from_file = fit_motors([read_capture(tmp_path / "cap.mf4")], options, "t")
    a, b = with_early.results[0].to_json(), from_file.results[0].to_json()
    # everything but the capture's name (in memory "dyno", from the file its path) is the same
    for key in ("status", "reasons", "k6", "c6", "phase_k6", "phase_c6", "delay_s", "harmonics", "fit", "hall_angle",
                "operating_point"):
        assert a[key] == b[key], key
    assert [{k: v for k, v in c.items() if k != "source"} for c in a["metrics"]["captures"]] == \
        [{k: v for k, v in c.items() if k != "source"} for c in b["metrics"]["captures"]]


def test_a_window_that_is_not_the_one_worked_on_is_computed_anew(tmp_path):
    early = EarlyWindows(poles=6, encoder_ppr=64)
    with DynoSimThread(DynoSim(synthetic_source, serial="E-2")) as dyno:
        cap = acquire(DynoConfig(port=dyno.port), SEGMENTS[:2], None, on_window=early.on_window)
    early.wait()
    from eol_cal.capture.windows import split_windows

    first, second = split_windows(cap)
    assert early.angle_of(first) is early._jobs[1].result()[1]
    changed = type(second)(second.t, {**second.channels, "hall": np.roll(second.channels["hall"], 1)},
                           dict(second.metadata), source=second.source)
    assert early.angle_of(changed) is not early._jobs[2].result()[1]
    # asked again (the fit asks several times about one window): the answer kept is the same
    assert early.angle_of(changed) is not early._jobs[2].result()[1]
    assert early.angle_of(first) is early._jobs[1].result()[1]
    assert early.used == 2
    early.close()


def test_the_verification_figures_are_the_ones_of_the_window(tmp_path):
    from eol_cal.analysis.angle import capture_angle
    from eol_cal.analysis.point_metrics import point_ripple
    from eol_cal.capture.windows import split_windows

    verify = EarlyWindows(poles=6, encoder_ppr=64, measure=point_ripple)
    with DynoSimThread(DynoSim(synthetic_source, serial="E-3")) as dyno:
        cap = acquire(DynoConfig(port=dyno.port), SEGMENTS[1:], None, on_window=verify.on_window)
    verify.wait()
    for window in split_windows(cap):
        early = verify.measured(window)
        again = point_ripple(window, capture_angle(window))
        assert early is verify._jobs[int(window.source.rsplit("#", 1)[1])].result()[2]
        assert early.to_dict() == again.to_dict()
    verify.close()
