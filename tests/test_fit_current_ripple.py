"""Issue 34: the ECU's own current ripple (kt * i_q) is known air-gap torque, not the motor's k6.

The current loop leaves a 6th-order ripple of its own in i_q; on the shaft it is torque like the
motor's. Fitted from the torque alone it lands in k6 (up to 1.2 % on plant motors, 2.8 % worst
over a lot); with the ``iq`` channel the fit takes it as known and k6 is the motor's own.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from eol_cal.analysis.fit import FitSpec, fit_segments
from eol_cal.analysis.fit.synth import synthetic_segments
from eol_cal.domain.bench_mechanics import load_mechanics, shaft_response
from eol_cal.domain.motor_params import load_motor
from eol_cal.numerics.wrap import wrap_pi

LOADS = (20.0, 60.0)


def _k6_err_pct(fit, k6: float) -> float:
    return 100.0 * (fit.harmonics[6]["k"].value - k6) / k6


@pytest.mark.parametrize("bench", [None, "resonant-250"])
def test_known_current_ripple_leaves_the_motors_own_k6(bench):
    # a current ripple of 2-4 % of k6 growing with speed and load, through a resonant torque path
    # and the transducer like the motor's: the fit must take it out, not attribute it to k6
    response = None
    if bench is not None:
        import functools

        response = functools.partial(shaft_response, motor=load_motor("paper"), mechanics=load_mechanics(bench))
    seg, truth = synthetic_segments(np.random.default_rng(3), seg_s=0.2, noise_nm=0.002, loads_a=LOADS,
                                    speeds_rpm=(300.0, 600.0), directions=(1, -1), iq6=(4e-6, 0.6),
                                    path_response=response)
    with_iq = fit_segments(seg, FitSpec())
    without = fit_segments(dataclasses.replace(seg, kt_iq=None), FitSpec())
    assert with_iq.converged and without.converged
    k = with_iq.harmonics[6]["k"]
    assert abs(_k6_err_pct(with_iq, truth["k6"])) < 0.5
    # within 4 standard errors (2 x the 95 % half-width): a 95 % interval alone misses 1 in 20
    assert abs(k.value - truth["k6"]) <= 2 * k.ci95
    assert abs(wrap_pi(k.phase - truth["phase_k6"])) <= max(2 * k.phase_ci95, math.radians(0.5))
    assert abs(with_iq.delay_s - truth["delay_s"]) <= 2 * with_iq.delay_ci95
    # the same data without the current: the ripple is fitted into k6 (what the fit did before)
    assert abs(_k6_err_pct(without, truth["k6"])) > 1.0
    assert with_iq.current is not None and without.current is None


def test_capture_without_iq_falls_back_and_says_so():
    from eol_cal.analysis.fit.capture import current_torque, motor_inputs
    from eol_cal.capture.synthetic import synthetic_capture

    cap = synthetic_capture(seed=2)
    if cap.has("iq"):
        cap = dataclasses.replace(cap, channels={k: v for k, v in cap.channels.items() if k != "iq"})
    (mi,) = motor_inputs([cap], frame="offline")
    assert mi.segments.kt_iq is None
    assert mi.current_ripple.startswith("fitted as the motor's: no iq channel in")
    assert cap.source in mi.current_ripple
    # with the channel every segment carries kt * iq, sample for sample
    iq = np.linspace(10.0, 11.0, len(cap.t))
    with_iq = dataclasses.replace(cap, channels={**cap.channels, "iq": iq})
    kt_iq, how = current_torque([with_iq], mi.info, mi.capture_of_segment, mi.kt)
    assert how.startswith("taken out")
    assert kt_iq is not None and len(kt_iq) == len(mi.info)
    o = mi.info[0]
    assert np.allclose(kt_iq[0], mi.kt * iq[o.start:o.stop])


@pytest.mark.slow  # six plant motors through eol-default
def test_plant_motors_whose_current_ripple_pushed_k6_over_half_a_percent():
    # seeds 1..6 of the production spread under the `best` estimator, simulated together (each
    # motor's noise and start follow its place in the batch): the torque alone gave k6 -1.20 % and
    # +0.94 % off the plant's for seeds 4 and 6 (the current loop's 6th-order ripple fitted into it)
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.analysis.fit.table import uncompensated_block
    from eol_cal.firmware.options import parse_options
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.variation import draw_motor

    best = parse_options("best")
    plants = [draw_motor(s) for s in range(1, 7)]
    prepared = [uncompensated_block(p.serial[:16], load_motor("paper"), calibrated_at=0, options=best) for p in plants]
    runs = simulate(plants, load_profile("eol-default"), mode="estimated", blocks=prepared, seed=1)
    for p, run in list(zip(plants, runs, strict=True))[3::2]:
        (mi,) = motor_inputs([run.capture], mechanics=load_mechanics("paper"), estimator_options=best)
        assert mi.current_ripple.startswith("taken out")
        fit = fit_segments(mi.segments, FitSpec())
        old = fit_segments(dataclasses.replace(mi.segments, kt_iq=None), FitSpec())
        assert abs(_k6_err_pct(fit, p.k6)) < 0.5, (p.serial, _k6_err_pct(fit, p.k6), _k6_err_pct(old, p.k6))
        assert abs(_k6_err_pct(old, p.k6)) > 0.5
        # the model now fits the torque: the lack of fit between segments all but gone
        assert fit.birge < 0.25 * old.birge


def _bench_coverage():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "bench" / "bench_coverage.py"
    spec = importlib.util.spec_from_file_location("bench_coverage", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow  # four plant motors through eol-default, fitted twice
def test_mechanical_orders_2_and_3_within_10_percent_and_3_deg():
    # mech23 seeds 1..4: the current loop answers the encoder's pulse placement at the mechanical
    # orders; credited to the motor's own orders it put order 2 off by 13.6 % and 3.6 deg
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.analysis.fit.motors import FitOptions, fit_inputs
    from eol_cal.firmware.options import parse_options
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.spread import load_spread
    from eol_cal.plant.variation import draw_motor

    bench = _bench_coverage()
    best = parse_options("best")
    plants = [draw_motor(s, spread=load_spread("mech23")) for s in range(1, 5)]
    _, runs, _ = bench.prepared_runs(plants, load_profile("eol-default"), best, 1, False)
    inputs = [motor_inputs([r.capture], mechanics=load_mechanics("paper"), estimator_options=best)[0] for r in runs]
    torque_only = [dataclasses.replace(mi, segments=dataclasses.replace(mi.segments, kt_iq=None)) for mi in inputs]
    worst = {}
    for name, ins in (("current known", inputs), ("torque only", torque_only)):
        results = fit_inputs(ins, FitOptions(capture_metrics=False, estimator_options=best)).results
        amp, phase = [], []
        for p, run, mi, res in zip(plants, runs, ins, results, strict=True):
            rows = {r["quantity"]: r for r in bench.motor_rows(p, run, mi, res, None)}
            assert res.status == "ok", (name, p.serial, res.reasons)
            for h in (2, 3):
                amp.append(abs(rows[f"mech{h}"]["err"]) / rows[f"mech{h}"]["truth"])
                phase.append(math.degrees(abs(rows[f"phase_mech{h}"]["err"])))
        worst[name] = (max(amp), max(phase))
    assert worst["current known"][0] <= 0.10 and worst["current known"][1] <= 3.0, worst
    assert worst["torque only"][0] > 0.10 or worst["torque only"][1] > 3.0, worst
