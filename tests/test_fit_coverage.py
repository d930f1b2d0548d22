"""Intervals that cover (issue 34, item 4), the small version of bench/bench_coverage.py: plant motors
of the mech23 spread through eol-default, fitted as the station fits, every reported 95 % interval
judged against the truth. 16 motors cannot tell 95 % from 90 %; they do tell the intervals 3-8 times
too narrow that the mechanical orders had before (a third of them covered), at a false-alarm rate
under 1 % per quantity (at least 12 of 16 when the coverage is 95 %), and the intervals 1.5-2.5x too
wide they had next (400 of 400 motors covered, bench/bench_coverage.py): pooled over the six
mechanical quantities (amplitude and phase of orders 1-3, 16 motors: 96 intervals), an interval that
covers 95 % misses at least once with probability 1 - 0.95^96 = 99.3 % (0.7 % false alarms: the six
of a motor share its data, so somewhat more), where the too-wide ones missed none in 2400."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

_BENCH = Path(__file__).resolve().parent.parent / "bench" / "bench_coverage.py"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_coverage", _BENCH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_reported_interval_covers_the_truth_on_plant_motors():
    from eol_cal.analysis.fit.capture import motor_inputs
    from eol_cal.analysis.fit.motors import FitOptions, fit_inputs
    from eol_cal.analysis.fit.table import uncompensated_block
    from eol_cal.firmware.options import parse_options
    from eol_cal.domain.bench_mechanics import load_mechanics
    from eol_cal.domain.motor_params import load_motor
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.spread import load_spread
    from eol_cal.plant.variation import draw_motor

    bench = _bench()
    best = parse_options("best")
    spread = load_spread("mech23")
    plants = [draw_motor(s, spread=spread) for s in range(2001, 2017)]
    prepared = [uncompensated_block(p.serial[:16], load_motor("paper"), calibrated_at=0, options=best) for p in plants]
    runs = simulate(plants, load_profile("eol-default"), mode="estimated", blocks=prepared, seed=2001)
    inputs = [motor_inputs([r.capture], mechanics=load_mechanics("paper"), estimator_options=best)[0] for r in runs]
    results = fit_inputs(inputs, FitOptions(capture_metrics=False, estimator_options=best)).results
    rows = []
    for p, run, mi, res in zip(plants, runs, inputs, results, strict=True):
        rows += bench.motor_rows(p, run, mi, res)
    assert sum(r["quantity"] == "status" for r in rows) <= 1  # a false model mismatch is rare
    cover = {q: (n, c) for q, n, c, _, _ in bench.summary(rows)}
    # k6 against the plant's own: the fit takes the ECU's current ripple out (the iq channel)
    for q in ("k6", "c6", "phase_c6", "delay_s", "mech1", "phase_mech1", "mech2", "phase_mech2",
              "mech3", "phase_mech3"):
        n, c = cover[q]
        assert n >= 15 and c >= 0.75, (q, n, c)
    # not too wide either: pooled, the mechanical intervals cover at most 99 % (see the docstring)
    mech = [r for r in rows if "mech" in r["quantity"]]
    assert len(mech) >= 90 and sum(abs(r["err"]) > r["ci95"] for r in mech) >= 1, len(mech)
    n, c = cover["fingerprint"]
    assert n > 1000 and 0.90 <= c <= 0.995, c
    # phase_k6: with the current's ripple known its interval is the fit's own (+-0.2 deg) plus the
    # firmware frame's uncertainty from the capture's segments (errors up to 0.5 deg)
    n, c = cover["phase_k6"]
    assert n >= 15 and c >= 0.75, ("phase_k6", n, c)


def test_the_intervals_follow_what_differs_from_segment_to_segment():
    """k6, c6, their phases and the delay at the segments' scatter (motor_fit.segment_scatter), on 200
    array-level motors of eol-default's shape (2 loads x 2 speeds x 2 directions: 8 segments) whose
    20 A segments carry a 6th-order torque of their own (what differs from segment to segment, as
    the plant's coloured noise and the path's gain against speed do). Each harmonic's lack-of-fit
    ratio spread over every direction and segment alike gave the delay an interval twice its errors
    (median |err|/ci95 0.18, covered 100 %; an interval that holds 95 % has 0.674 / 1.96 = 0.34):
    the median of 200 is within +-0.05 of its value, so [0.25, 0.5] tells the two apart."""
    import numpy as np

    from eol_cal.analysis.fit.synth import synthetic_segments

    rng = np.random.default_rng(7)
    segs, truths = [], []
    for _ in range(200):
        seg, truth = synthetic_segments(rng, seg_s=0.05, noise_nm=0.01, loads_a=(20.0, 65.0), speeds_rpm=(300.0, 600.0),
                                        directions=(1, -1), mech_nm=0.0)
        for s in range(seg.n_segments):
            if abs(seg.i_qo[s]) < 30:
                z = complex(*rng.normal(0.0, 0.002, 2))
                seg.torque[s] = seg.torque[s] + abs(z) * np.sin(6 * seg.theta[s] + np.angle(z))
        segs.append(seg)
        truths.append(truth)
    for q, r in _error_ratios(segs, truths).items():
        med, cover = float(np.median(r)), float(np.mean(np.array(r) <= 1.0))
        assert 0.25 <= med <= 0.5 and cover >= 0.84, (q, med, cover)


def test_white_noise_keeps_the_noise_as_the_floor_of_the_scatter():
    """The reason each interval is the wider of the noise's and the segments' scatter, not the scatter
    alone: on eol-default's 8 segments (2 loads x 2 speeds x 2 directions) with white noise and an
    exact model, the cluster estimate of 8 segments falls short where few segments carry a parameter
    (their residuals are small by their own leverage): alone, with Student's t of 7 dof, it covered
    the delay 83 %, c6 88-89 %, k6 91-92 % of 1000 such motors, where the noise's (then the truth)
    covered 94-96 % and the wider of the two 94.1-96.5 % (93.5-97 % with t(7) on the whole scatter
    where it was the wider; on plant motors the scatter is the wider on most motors: docs/fit.md).
    400 motors: a coverage of 93.5 % stays above 90 % with probability 0.998; the scatter alone's
    83 % for the delay never reaches it (here 83.5 %, c6 86 %)."""
    import numpy as np

    from eol_cal.analysis.fit.synth import synthetic_segments

    rng = np.random.default_rng(12)
    segs, truths = [], []
    for _ in range(400):
        seg, truth = synthetic_segments(rng, seg_s=0.05, noise_nm=0.01, loads_a=(20.0, 65.0), speeds_rpm=(300.0, 600.0),
                                        directions=(1, -1), mech_nm=0.0)
        segs.append(seg)
        truths.append(truth)
    cover = {q: float(np.mean(np.array(r) <= 1.0)) for q, r in _error_ratios(segs, truths).items()}
    assert all(0.90 <= c <= 0.99 for c in cover.values()), cover


def test_the_noise_is_the_one_at_the_6th_not_the_residuals_average():
    """The noise's interval at the noise the 6th has (segment_noise beside the line, motor_fit.at_line_noise),
    not the residual's average taken as white: 300 motors of eol-default's 8 segments whose torque
    noise is white (0.01 N*m) plus as much again differenced (a first difference: nearly all of it far
    above the 6th), so the residual's variance is three times the noise at the 6th. At the average the
    noise's interval is sqrt(3) too wide and k6, c6, their phases and the delay covered 99.7-100 %; at
    the line's own noise 93-97 % (white noise alone, the same at both: test above)."""
    import numpy as np

    from eol_cal.analysis.fit.synth import synthetic_segments

    rng = np.random.default_rng(21)
    segs, truths = [], []
    for _ in range(300):
        seg, truth = synthetic_segments(rng, seg_s=0.05, noise_nm=0.01, loads_a=(20.0, 65.0), speeds_rpm=(300.0, 600.0),
                                        directions=(1, -1), mech_nm=0.0)
        seg.torque = [y + 0.01 * np.diff(rng.standard_normal(len(y) + 1)) for y in seg.torque]
        segs.append(seg)
        truths.append(truth)
    cover = {q: float(np.mean(np.array(r) <= 1.0)) for q, r in _error_ratios(segs, truths, line_noise=True).items()}
    assert all(0.90 <= c <= 0.985 for c in cover.values()), cover


def test_the_quantile_follows_the_scatters_excess_over_the_noise():
    """Student's t of the Welch-Satterthwaite degrees of freedom (motor_fit.wider_per_quantity): a
    scatter all excess over the noise takes t(S - 1); one barely over the noise the normal's 1.96,
    as the noise's own (t(7) on the whole scatter, before, made an interval 1.2x the noise's there
    and k6, c6 and the delay covered 98.25-98.75 % of 400 plant motors); the noise where wider."""
    import numpy as np
    from scipy.special import stdtrit

    from eol_cal.analysis.fit.model import Z95
    from eol_cal.analysis.fit.motor_fit import wider_per_quantity

    blocks = [slice(0, 1), slice(1, 3)]
    noise = np.diag([1.0, 1.0, 1.0])
    t7 = float(stdtrit(7, 0.975)) / Z95
    cov = wider_per_quantity(noise, np.diag([1e6, 1.01, 1.01]), blocks, 8)
    assert cov[0, 0] / 1e6 == pytest.approx(t7 ** 2, rel=1e-5)  # all excess: t(7)
    assert np.sqrt(np.diag(cov)[1:]) == pytest.approx(np.sqrt(1.01), rel=1e-4)  # 1 % over: ~1.96
    cov = wider_per_quantity(noise, np.diag([0.5, 0.9, 0.9]), blocks, 8)
    assert np.array_equal(cov, noise)  # the noise where it is the wider
    # the excess's share: V = 2 V_n gives nu = 4 (S - 1)
    cov = wider_per_quantity(noise, np.diag([2.0, 1.0, 1.0]), blocks, 8)
    assert cov[0, 0] == pytest.approx(2.0 * (float(stdtrit(28, 0.975)) / Z95) ** 2, rel=1e-9)


def _error_ratios(segs: list, truths: list[dict[str, float]], line_noise: bool = False) -> dict[str, list[float]]:
    """|error| / ci95 of k6, c6, their phases and the delay, fitted (6th only) on ``segs``; with
    ``line_noise`` the intervals at the noise the 6th has (as the station's results take them)."""
    from eol_cal.analysis.fit import FitSpec, fit_many
    from eol_cal.analysis.fit.motor_fit import at_line_noise
    from eol_cal.analysis.fit.segment_noise import segment_noise
    from eol_cal.numerics.wrap import wrap_pi

    spec = FitSpec(harmonics=(6,))
    ratios: dict[str, list[float]] = {q: [] for q in ("k6", "phase_k6", "c6", "phase_c6", "delay_s")}
    for seg, f, t in zip(segs, fit_many(segs, spec), truths, strict=True):
        if line_noise:
            f = at_line_noise(f, spec, segment_noise(seg, spec, f.delay_s).row_variance())
        six = f.harmonics[6]
        for part in ("k", "c"):
            ratios[f"{part}6"].append(abs(six[part].value - t[f"{part}6"]) / six[part].ci95)
            ratios[f"phase_{part}6"].append(abs(float(wrap_pi(six[part].phase - t[f"phase_{part}6"]))) / six[part].phase_ci95)
        ratios["delay_s"].append(abs(f.delay_s - t["delay_s"]) / f.delay_ci95)
    return ratios
