"""The ripple fit at the array level: recovery, exactness, identifiability, convergence, coverage."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.analysis.fit import FitSpec, fit_many, fit_segments
from eol_cal.numerics.wrap import wrap_pi
from eol_cal.analysis.fit.synth import synthetic_segments
from eol_cal.analysis.result import STATUS_CI_TOO_WIDE, STATUS_NOT_CONVERGED, STATUS_OK, CiLimits, judge, motor_result
from eol_cal.errors import InputError

# three load points: with two speeds (or two directions) six segments, one compiled shape for most tests
LOADS = (20.0, 40.0, 65.0)


def _phase_err(a: float, b: float) -> float:
    return abs(wrap_pi(a - b))


def _within(est, truth: float, sigmas: float = 4.0) -> bool:
    return abs(est.value - truth) <= sigmas * est.ci95 / 1.96


@pytest.mark.slow
def test_recovers_known_parameters_with_noise():
    seg, truth = synthetic_segments(np.random.default_rng(11), seg_s=0.15, noise_nm=0.01, loads_a=LOADS)
    f = fit_segments(seg, FitSpec())
    assert f.converged and f.steps <= 10
    k, c = f.harmonics[6]["k"], f.harmonics[6]["c"]
    assert _within(k, truth["k6"]) and abs(k.value - truth["k6"]) < 0.05 * truth["k6"]
    assert _phase_err(k.phase, truth["phase_k6"]) <= 4 * k.phase_ci95 / 1.96
    assert _within(c, truth["c6"])
    assert _phase_err(c.phase, truth["phase_c6"]) <= 4 * c.phase_ci95 / 1.96
    assert abs(f.delay_s - truth["delay_s"]) <= 4 * f.delay_ci95 / 1.96
    # T_avg per segment: kt * i_qo plus the drift's mean over the segment
    kt = 0.04905
    expect = kt * seg.i_qo + 0.01 * 0.075
    assert np.allclose(f.t_avg, expect, atol=2e-3)
    assert abs(f.rms - 0.01) < 5e-4  # the noise is all that is left


@pytest.mark.slow
def test_exact_same_optimum_as_full_per_sample_least_squares():
    """The compressed, nuisance-projected JAX problem has the same optimum as scipy on every sample."""
    from eol_cal.analysis.fit.scipy_ref import fit_segments_scipy

    seg, _ = synthetic_segments(np.random.default_rng(5), seg_s=0.02, speeds_rpm=(600.0, 1200.0), loads_a=LOADS)
    spec = FitSpec()
    f = fit_segments(seg, spec)
    ref = fit_segments_scipy(seg, spec)
    for part in ("c", "k"):
        amp, ph = ref["harmonics"][6][part]
        assert f.harmonics[6][part].value == pytest.approx(amp, rel=1e-5)
        assert _phase_err(f.harmonics[6][part].phase, ph) < 1e-5
    assert f.delay_s == pytest.approx(ref["delay_s"], rel=1e-5)
    assert 0.5 * f.rms**2 * f.n_samples == pytest.approx(ref["cost"], rel=1e-9)


@pytest.mark.slow
def test_both_directions_one_speed_identify_the_delay():
    # the pure-delay transducer model here (the default is the first-order low-pass)
    seg, truth = synthetic_segments(
        np.random.default_rng(2), seg_s=0.15, speeds_rpm=(600.0,), directions=(1, -1), loads_a=LOADS,
        transducer="delay",
    )
    assert (seg.omega_e < 0).any() and (seg.omega_e > 0).any()
    f = fit_segments(seg, FitSpec(transducer="delay"))
    assert f.converged
    assert abs(f.delay_s - truth["delay_s"]) <= 4 * f.delay_ci95 / 1.96 and f.delay_ci95 < 0.5 * truth["delay_s"]
    k = f.harmonics[6]["k"]
    assert abs(k.value - truth["k6"]) < 0.05 * truth["k6"]
    assert _phase_err(k.phase, truth["phase_k6"]) < 0.05
    # negative load in reverse (motoring backwards) keeps the sign convention: T_avg follows i_qo
    assert np.all(np.sign(f.t_avg) == np.sign(seg.i_qo))


@pytest.mark.slow  # ~6 s on a quiet machine (CONTRIBUTING.md, "Fast or slow")
def test_higher_harmonics():
    extra = {12: (0.002, 0.7, 0.0002, -2.0), 18: (0.001, 2.5, 0.0, 0.0)}
    seg, _ = synthetic_segments(np.random.default_rng(8), seg_s=0.15, noise_nm=0.003, extra=extra, loads_a=LOADS)
    f = fit_segments(seg, FitSpec())
    assert f.converged
    h12 = f.harmonics[12]
    assert abs(h12["c"].value - 0.002) < 3e-4 and _phase_err(h12["c"].phase, 0.7) < 0.15
    assert abs(h12["k"].value - 0.0002) < 2e-5 and _phase_err(h12["k"].phase, -2.0) < 0.1
    assert abs(f.harmonics[18]["c"].value - 0.001) < 3e-4
    # the 18th has no load part: its estimate is compatible with zero
    assert f.harmonics[18]["k"].value <= 4 * f.harmonics[18]["k"].ci95 / 1.96


def test_c6_and_k6_from_a_single_load_point_refused():
    seg, _ = synthetic_segments(np.random.default_rng(0), seg_s=0.05, loads_a=(65.0,))
    with pytest.raises(InputError, match="single load point"):
        fit_segments(seg, FitSpec())


def test_delay_from_a_single_speed_refused_unless_given():
    seg, truth = synthetic_segments(np.random.default_rng(0), seg_s=0.05, speeds_rpm=(600.0,))
    with pytest.raises(InputError, match="delay"):
        fit_segments(seg, FitSpec())


def test_paper_case_k6_only_one_load_known_delay():
    """Seed eq. (17): k6 alone from one load point, the delay given (here none)."""
    seg, truth = synthetic_segments(np.random.default_rng(0), seg_s=0.1, loads_a=(65.0,), c6=0.0, delay_s=0.0)
    f = fit_segments(seg, FitSpec(fit_c=False, delay_s=0.0))
    assert f.converged and "c" not in f.harmonics[6]
    assert f.delay_s == 0.0 and f.delay_ci95 == 0.0
    k = f.harmonics[6]["k"]
    assert _within(k, truth["k6"]) and _phase_err(k.phase, truth["phase_k6"]) <= 4 * k.phase_ci95 / 1.96


@pytest.mark.slow
def test_non_convergence_is_reported_never_as_a_result():
    seg, _ = synthetic_segments(np.random.default_rng(4), seg_s=0.05, delay_s=6e-4, loads_a=LOADS)
    spec = FitSpec(max_steps=1)
    f = fit_segments(seg, spec)
    assert not f.converged and f.steps == 1
    status, reasons = judge(f, spec, CiLimits())
    assert status == STATUS_NOT_CONVERGED and reasons
    res = motor_result(
        "X", f, spec, CiLimits(), kt=0.049, kt_source="test", poles=6, encoder_ppr=64, sources=[],
        segments=[{"i_qo_a": 20.0, "speed_rpm": 300.0}], metrics={}, solver_mode="loop",
    )
    # the result keeps how the solver ended, not only that it failed
    assert res.status == STATUS_NOT_CONVERGED and res.estimates is None and not res.usable
    assert f.solver_result == res.solver_result != "successful"
    rec = res.to_json()
    for key in ("k6", "phase_k6", "c6", "phase_c6", "delay_s", "harmonics"):
        assert rec[key] is None
    assert rec["status"] == "not_converged" and rec["fit"]["converged"] is False


@pytest.mark.slow  # ~4 s on a quiet machine (CONTRIBUTING.md, "Fast or slow")
def test_interval_wider_than_limit_is_not_a_result():
    seg, _ = synthetic_segments(np.random.default_rng(4), seg_s=0.05, noise_nm=0.2, loads_a=LOADS)
    # one mechanical pair per segment: with three (the default) these 0.05 s segments at 0.2 N*m
    # noise no longer pin the delay, and the test is about judging the intervals of a fit that converged
    spec = FitSpec(mech_orders=1)
    f = fit_segments(seg, spec)
    assert f.converged
    assert judge(f, spec, CiLimits(k6_rel=1.0, phase_k6_deg=180.0, c6_nm=1.0))[0] == STATUS_OK
    status, reasons = judge(f, spec, CiLimits())
    assert status == STATUS_CI_TOO_WIDE and any("k6" in r for r in reasons)


@pytest.mark.slow
def test_batched_equals_single_and_95_percent_intervals_cover_the_truth():
    """Over 200 seeds each 95 % interval holds the truth at about that rate (0.90-0.99)."""
    rng = np.random.default_rng(2024)
    motors, truths = [], []
    for _ in range(200):
        truth = dict(
            k6=rng.uniform(4e-4, 8e-4), phase_k6=rng.uniform(-math.pi, math.pi), c6=rng.uniform(3e-3, 6e-3),
            phase_c6=rng.uniform(-math.pi, math.pi), delay_s=rng.uniform(5e-5, 3e-4),
        )
        seg, _ = synthetic_segments(rng, seg_s=0.03, noise_nm=0.01, speeds_rpm=(600.0, 1200.0), loads_a=LOADS, **truth)
        motors.append(seg)
        truths.append(truth)
    spec = FitSpec()
    fits = fit_many(motors, spec, mode="map", chunk=200)
    again = [fit_segments(m, spec) for m in motors[:5]]
    for a, b in zip(fits[:5], again, strict=True):
        assert a.harmonics[6]["k"].value == pytest.approx(b.harmonics[6]["k"].value, rel=1e-9)
        assert a.delay_s == pytest.approx(b.delay_s, rel=1e-9)
    assert all(f.converged for f in fits)
    hits = {"k6": 0, "phase_k6": 0, "c6": 0, "phase_c6": 0, "delay_s": 0}
    for f, t in zip(fits, truths, strict=True):
        k, c = f.harmonics[6]["k"], f.harmonics[6]["c"]
        hits["k6"] += abs(k.value - t["k6"]) <= k.ci95
        hits["phase_k6"] += _phase_err(k.phase, t["phase_k6"]) <= k.phase_ci95
        hits["c6"] += abs(c.value - t["c6"]) <= c.ci95
        hits["phase_c6"] += _phase_err(c.phase, t["phase_c6"]) <= c.phase_ci95
        hits["delay_s"] += abs(f.delay_s - t["delay_s"]) <= f.delay_ci95
    rates = {k: v / len(fits) for k, v in hits.items()}
    for name, rate in rates.items():
        assert 0.90 <= rate <= 0.99, (name, rates)


@pytest.mark.slow
def test_exported_solver_round_trip(tmp_path):
    """The CLI's serialized solver (jax.export) gives the same fit as the jitted one."""
    from eol_cal.analysis.fit import cache

    seg, _ = synthetic_segments(np.random.default_rng(9), seg_s=0.1, loads_a=(65.0,), c6=0.0, delay_s=0.0)
    spec = FitSpec(fit_c=False, delay_s=0.0)
    first = fit_segments(seg, spec, cache_dir=tmp_path)  # traced, exported, and the export read back used
    files = list(tmp_path.glob("fit-*.jaxexport"))
    assert len(files) == 1 and files[0].stat().st_size > 1000
    assert files[0] in cache._LOADED  # the next process compiles nothing the first did not
    assert cache.load_solver(tmp_path, spec, seg.n_segments, 1) is not None
    second = fit_segments(seg, spec, cache_dir=tmp_path)  # deserialized
    assert second.harmonics[6]["k"].value == first.harmonics[6]["k"].value
    assert second.harmonics[6]["k"].ci95 == first.harmonics[6]["k"].ci95 and second.steps == first.steps


@pytest.mark.slow
def test_a_corrupt_solver_file_costs_only_the_tracing(tmp_path):
    """A cache entry that does not deserialize (a torn disk, another jax's file under the same key)
    is passed over: the fit is the one without a cache, and the entry is written anew."""
    from eol_cal.analysis.fit import cache

    seg, _ = synthetic_segments(np.random.default_rng(9), seg_s=0.1, loads_a=(65.0,), c6=0.0, delay_s=0.0)
    spec = FitSpec(fit_c=False, delay_s=0.0)
    path = cache.solver_file(tmp_path, spec, seg.n_segments, 1)
    path.write_bytes(b"\x00garbage" * 100)
    assert cache.load_solver(tmp_path, spec, seg.n_segments, 1) is None
    got = fit_segments(seg, spec, cache_dir=tmp_path)
    plain = fit_segments(seg, spec)
    assert got.harmonics[6]["k"].value == plain.harmonics[6]["k"].value and got.steps == plain.steps
    assert path.read_bytes()[:9] != b"\x00garbage"  # replaced by a readable one


@pytest.mark.slow
def test_cache_directory_is_a_parameter(tmp_path):
    """The cache directory comes from the caller (default: one function of the environment), and a
    fit without one writes nothing."""
    from pathlib import Path

    from eol_cal.analysis.fit import cache

    assert cache.default_cache_dir({"EOL_CAL_JAX_CACHE": "off"}) is None
    assert cache.default_cache_dir({"EOL_CAL_JAX_CACHE": str(tmp_path / "c")}) == tmp_path / "c"
    assert cache.default_cache_dir({}) == Path.home() / ".cache" / "eol-cal" / "jax"
    assert cache.enable_compile_cache(None) is None
    seg, _ = synthetic_segments(np.random.default_rng(9), seg_s=0.1, loads_a=(65.0,), c6=0.0, delay_s=0.0)
    spec = FitSpec(fit_c=False, delay_s=0.0)
    assert cache.load_solver(None, spec, seg.n_segments, 1) is None
    # two directories in one process: each fit uses the one it is given
    for d in (tmp_path / "a", tmp_path / "b"):
        fit_segments(seg, spec, cache_dir=d)
        assert len(list(d.glob("fit-*.jaxexport"))) == 1
