"""Closing the loop on the plant: simulate, fit, make the block, simulate compensated: p-p drops."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from eol_cal.analysis.fit import FitSpec, fit_many
from eol_cal.numerics.wrap import wrap_pi
from eol_cal.analysis.fit.capture import motor_inputs
from eol_cal.analysis.fit.table import block_from_result
from eol_cal.analysis.metrics import capture_ripple_pp
from eol_cal.analysis.result import CiLimits, motor_result
from eol_cal.firmware.block import check, pack
from eol_cal.domain.motor_params import load_motor
from eol_cal.plant.presets import paper
from eol_cal.plant.profile import Profile, ProfileSegment
from eol_cal.plant.ecu_model import true_block
from eol_cal.plant.simulate import simulate


@pytest.mark.slow
def test_fit_table_and_compensated_plant_close_the_loop():
    spec = paper()
    # Both runs use the compensated controller (one compiled plant); zero tables = no i_qc.
    ideal = true_block(spec)
    off = dataclasses.replace(ideal, table_const=np.zeros(ideal.table_len, np.float32),
                              table_per_amp=np.zeros(ideal.table_len, np.float32))
    # short calibration: two loads forward, one load in reverse (the reverse speed makes the
    # transducer lag identifiable)
    cal = Profile("cal", (ProfileSegment(120.0, 0.5, iq=20.0), ProfileSegment(120.0, 0.5, iq=65.0, ramp_s=0.05),
                          ProfileSegment(-120.0, 0.6, iq=-65.0, ramp_s=0.15)))
    (run,) = simulate(spec, cal, mode="compensated", blocks=off, seed=3)
    (mi,) = motor_inputs([run.capture])
    assert len(mi.info) == 3
    fs = FitSpec()
    (fit,) = fit_many([mi.segments], fs)
    segs = [{"i_qo_a": i.i_qo, "speed_rpm": i.speed_rpm} for i in mi.info]
    res = motor_result(mi.serial, fit, fs, CiLimits(), kt=mi.kt, kt_source=mi.kt_source, poles=mi.poles,
                       encoder_ppr=mi.encoder_ppr, sources=[], segments=segs, metrics={}, solver_mode="loop")
    assert res.status == "ok" and res.estimates is not None, res.reasons
    e = res.estimates
    assert abs(e.k6.value - spec.k6) < 0.05 * spec.k6
    assert abs(wrap_pi(e.phase_k6.value - spec.phase_k6)) < math.radians(3)
    # the plant's transducer is a first-order low-pass; the fit's time constant should match it
    assert abs(e.delay_s.value - 1 / (2 * math.pi * spec.tq_bw_hz)) < 0.2 / (2 * math.pi * spec.tq_bw_hz)
    block = block_from_result(res, load_motor("paper"))
    assert check(pack(block)).valid

    point = Profile("check", (ProfileSegment(120.0, 0.6, iq=65.0),))
    (before,) = simulate(spec, point, mode="compensated", blocks=off, seed=4)
    (after,) = simulate(spec, point, mode="compensated", blocks=block, seed=4)
    pp0 = capture_ripple_pp(before.capture).filtered_pct
    pp1 = capture_ripple_pp(after.capture).filtered_pct
    assert pp1 < 0.5 * pp0, (pp0, pp1)
