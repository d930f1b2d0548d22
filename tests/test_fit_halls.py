"""The measured hall table: recovery, refusals, and what it buys the ECU's angle on the plant."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.analysis.halls import measure_hall_angles
from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE

#: state that begins at each of the plant's hall switching points (U rise, U fall, V rise, V fall,
#: W rise, W fall: eol_cal.firmware.kinematics), forward rotation 5 1 3 2 6 4
STATE_OF_EDGE = (5, 2, 3, 4, 6, 1)


def test_measure_recovers_offsets_and_refuses_what_it_cannot_measure():
    rng = np.random.default_rng(3)
    offsets = np.radians([0.8, -0.5, 0.3, -1.2, 0.0, 0.6])
    begins, theta = [], []
    for _ in range(3):  # three windows, 20 transitions of each boundary in each
        b = np.tile(np.arange(1, 7), 20)
        th = np.asarray(NOMINAL_HALL_ANGLE)[b - 1] + offsets[b - 1] + rng.normal(0, math.radians(0.2), b.size)
        begins.append(b)
        theta.append(np.mod(th, 2 * math.pi))
    h = measure_hall_angles(begins, theta)
    assert h.source == "measured" and h.n_transitions == (60,) * 6
    assert np.allclose(h.deviation_rad, offsets, atol=math.radians(0.1))
    assert np.allclose(np.angle(np.exp(1j * (np.asarray(h.hall_angle) - np.asarray(NOMINAL_HALL_ANGLE) - offsets))), 0,
                       atol=math.radians(0.1))
    assert all(0 <= a < 2 * math.pi for a in h.hall_angle)
    assert all(math.radians(0.1) < s < math.radians(0.3) for s in h.scatter_rad)
    d = h.to_dict()
    assert d["source"] == "measured" and len(d["value"]) == 6 and abs(d["deviation_deg"][3] + 1.2) < 0.1

    few = measure_hall_angles([begins[0][begins[0] != 4][:50]], [theta[0][begins[0] != 4][:50]])
    assert few.source.startswith("nominal") and "state 4" in few.source
    assert few.hall_angle == tuple(float(a) for a in NOMINAL_HALL_ANGLE)
    broken = measure_hall_angles([begins[0]], [np.where(begins[0] == 2, theta[0] + math.radians(40), theta[0])])
    assert broken.source.startswith("nominal") and "state 2" in broken.source and "+39.5 deg" in broken.source


@pytest.fixture(scope="module")
def plant_motor():
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.domain.bench_mechanics import load_mechanics
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.variation import draw_motor

    spec = draw_motor(4)  # hall errors about 1 degree RMS
    (run,) = simulate(spec, load_profile("eol-default"), mode="estimated", seed=2)
    (mi,) = motor_inputs([run.capture], mechanics=load_mechanics("paper"))
    return spec, run, mi


def test_measured_table_matches_the_plants_hall_errors(plant_motor):
    spec, run, mi = plant_motor
    assert mi.hall.source == "measured" and min(mi.hall.n_transitions) >= 10
    true = np.zeros(6)
    for edge, s in enumerate(STATE_OF_EDGE):
        true[s - 1] = math.radians(spec.hall_err_deg[edge])
    # the offline frame sits on the halls' mean: compare in it
    d_rec = float(np.angle(np.mean(np.exp(1j * (mi.angles[0].theta_r - run.theta_r)))))
    err = np.angle(np.exp(1j * (np.asarray(mi.hall.deviation_rad) - true - d_rec)))
    assert np.abs(err).max() < math.radians(0.5), np.degrees(err)
    assert np.sqrt(np.mean(true**2)) > math.radians(0.7)  # the motor's errors are well above that


def test_measured_table_brings_the_ecu_angle_closer(plant_motor):
    """The firmware estimator run with the measured table: its angle error about its own mean
    (what the compensation sees as jitter) is smaller than with the nominal table."""
    from eol_cal.analysis.firmware_angle import firmware_config
    from eol_cal.firmware import estimator as est

    spec, run, mi = plant_motor
    c = run.capture
    keep = np.zeros(len(c.t), bool)
    for info in mi.info:  # the steady segments (ramps and the reversal are the estimator's own story)
        keep[info.start:info.stop] = True
    rms = {}
    for name, table in (("nominal", None), ("measured", mi.hall.hall_angle)):
        out = est.run_jax_chunked(firmware_config(c), c["enc_a"], c["enc_b"], c["hall"], hall_angle=table)
        d = np.angle(np.exp(1j * (np.asarray(out.theta_hat, float) - run.theta_r)))[keep]
        d = np.angle(np.exp(1j * (d - np.angle(np.mean(np.exp(1j * d))))))
        rms[name] = float(np.degrees(np.sqrt(np.mean(d**2))))
    assert rms["measured"] < 0.85 * rms["nominal"], rms


@pytest.mark.slow
def test_record_and_block_carry_the_measured_table(plant_motor):
    from eol_cal.analysis.fit import FitSpec, fit_many
    from eol_cal.analysis.fit.table import block_from_result
    from eol_cal.analysis.result import CiLimits, result_for_motor
    from eol_cal.domain.motor_params import load_motor

    _, _, mi = plant_motor
    (f,) = fit_many([mi.segments], FitSpec())
    res = result_for_motor(mi, f, FitSpec(), CiLimits(), metrics={}, solver_mode="loop")
    assert res.status == "ok", res.reasons
    assert res.hall_angle is not None and res.hall_angle["source"] == "measured"
    block = block_from_result(res, load_motor("paper"))
    assert np.allclose(block.hall_angle, mi.hall.hall_angle)
    assert not np.allclose(block.hall_angle, NOMINAL_HALL_ANGLE, atol=math.radians(0.2))


@pytest.mark.parametrize("kwargs", [{"hall_angle": "measure"}, {"frame": "ecu"}])
def test_unknown_option_values_are_refused_not_taken_as_a_default(kwargs):
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.capture.synthetic import synthetic_capture
    from eol_cal.errors import InputError

    cap = synthetic_capture(rpm=60.0, i_qo=20.0, seconds=0.35, serial="M-1")
    with pytest.raises(InputError) as exc:
        motor_inputs([cap], **kwargs)
    assert exc.value.field == next(iter(kwargs)) and "unknown value" in str(exc.value)
