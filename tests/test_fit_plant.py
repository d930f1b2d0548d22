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


@pytest.mark.slow  # two plant motors through eol-default
def test_noiseless_plant_motors_k6_within_0_06_percent_and_the_transducer_lag_within_10_us():
    # issue 34: the plant's sampled torque chain led its continuous model by 25 us (the reading
    # recorded after the tick's update, the ripple at the tick's start angle), which the fit's
    # 60 Hz low-pass took as a shorter time constant and so a lower gain: k6 -0.12 .. -0.13 % and
    # the lag 26-28 us short on these motors, noise-free, every motor alike
    from eol_cal.analysis.fit import fit_segments
    from eol_cal.analysis.fit.table import uncompensated_block
    from eol_cal.domain.bench_mechanics import load_mechanics
    from eol_cal.firmware.options import parse_options
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.spread import load_spread
    from eol_cal.plant.variation import draw_motor

    best = parse_options("best")
    # no noise, ideal encoder and halls, no mechanical orders (their leak scatters k6 by +-0.1 %
    # without noise): what is left is the chain
    plants = [draw_motor(s, spread=load_spread("mech23")).replace(
        tq_noise_nm=0.0, i_noise_a=0.0, tq_lsb_nm=1e-7, i_lsb_a=1e-5, enc_edge_err_deg=(), hall_err_deg=(0.0,) * 6,
        unb1=0.0, unb2=0.0, unb3=0.0) for s in (3001, 3002)]
    prepared = [uncompensated_block(p.serial[:16], load_motor("paper"), calibrated_at=0, options=best) for p in plants]
    runs = simulate(plants, load_profile("eol-default"), mode="estimated", blocks=prepared, seed=3001)
    for p, run in zip(plants, runs, strict=True):
        (mi,) = motor_inputs([run.capture], mechanics=load_mechanics("paper"), estimator_options=best)
        fit = fit_segments(mi.segments, FitSpec())
        assert fit.converged
        k6 = float(fit.harmonics[6]["k"].value)
        tau = 1.0 / (2 * math.pi * p.tq_bw_hz)
        # 0.06 %: the old chain's -0.12 % fails it. SIM-003001 gives -0.017 % under XLA's default
        # and -0.046 % when the process runs XLA's tick loops as one kernel (numerics.xla.configure_xla,
        # which the CLI and the benchmarks call and an earlier test in the same worker may): the
        # fusion's float32 rounding, carried through the plant's ticks into a noiseless fit
        assert abs(k6 - p.k6) < 0.0006 * p.k6, (p.serial, 100 * (k6 / p.k6 - 1))
        assert abs(fit.delay_s - tau) < 10e-6, (p.serial, 1e6 * (fit.delay_s - tau))
