"""The firmware estimator's angle (what the ECU sees) against the offline angle."""

import numpy as np
import pytest

from eol_cal.analysis.angle import capture_angle
from eol_cal.analysis.firmware_angle import firmware_angle_difference
from eol_cal.capture.data import Capture
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.errors import InputError


@pytest.mark.slow
def test_estimator_tracks_the_offline_angle_and_the_raw_angle_does_not():
    cap = synthetic_capture(rpm=60.0, seconds=0.6, theta_r0=0.5)
    d = firmware_angle_difference(cap, capture_angle(cap))
    assert d.n_ticks > 0.5 * len(cap.t)
    # the paper's estimator interpolates between edges: far below one count (16.875 deg)
    assert d.rms_deg < 0.5 and d.max_deg < 2.0
    assert d.phase6_shift_deg == pytest.approx(6 * d.mean_deg)
    # the raw edge angle is the sawtooth of one count: RMS count/sqrt(3)
    assert d.raw_rms_deg == pytest.approx(16.875 / np.sqrt(3), rel=0.05)
    assert d.raw_max_deg == pytest.approx(16.875, rel=0.05)


def test_estimator_needs_channel_b():
    cap = synthetic_capture(seconds=0.3)
    no_b = Capture(t=cap.t, channels={k: v for k, v in cap.channels.items() if k != "enc_b"},
                   metadata=cap.metadata, source="x.csv")
    with pytest.raises(InputError) as exc:
        firmware_angle_difference(no_b)
    assert exc.value.field == "enc_b" and exc.value.file == "x.csv"
