"""The batch mode fit_many(mode="auto") picks (eol_cal/analysis/fit/batch.py): vmap from
AUTO_BATCH_MIN motors on (issue 37: its solve measured the faster), its fits those of map and of
the one-motor loop within the batch's 1e-9."""

import numpy as np
import pytest

from eol_cal.analysis import fit
from eol_cal.analysis.fit.synth import synthetic_segments


def test_auto_picks_vmap_for_a_batch_and_the_loop_below() -> None:
    assert fit.pick_mode(fit.AUTO_BATCH_MIN) == "vmap"
    assert fit.pick_mode(fit.AUTO_BATCH_MIN - 1) == "loop"


def test_auto_batch_fits_equal_map_and_loop_within_1e9() -> None:
    rng = np.random.default_rng(37)
    motors = [synthetic_segments(rng, seg_s=0.05, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0),
                                 k6=rng.uniform(4e-4, 8e-4), phase_k6=rng.uniform(-3, 3))[0]
              for _ in range(fit.AUTO_BATCH_MIN)]
    spec = fit.FitSpec()
    auto = fit.fit_many(motors, spec, chunk=fit.AUTO_BATCH_MIN, threads=0)
    mapped = fit.fit_many(motors, spec, mode="map", chunk=fit.AUTO_BATCH_MIN, threads=0)
    looped = [fit.fit_segments(m, spec) for m in motors[:3]]
    for a, b in [*zip(auto, mapped, strict=True), *zip(auto, looped, strict=False)]:
        assert a.converged and b.converged
        for h in (6, 12, 18):
            for part in ("c", "k"):
                ea, eb = a.harmonics[h][part], b.harmonics[h][part]
                assert ea.value == pytest.approx(eb.value, rel=1e-9)
                assert ea.phase == pytest.approx(eb.phase, rel=1e-9)
                assert ea.ci95 == pytest.approx(eb.ci95, rel=1e-9)
        assert a.delay_s == pytest.approx(b.delay_s, rel=1e-9)
        np.testing.assert_allclose(a.t_avg, b.t_avg, rtol=1e-12)


@pytest.mark.slow  # a batched solver traced, exported and read back (2-6 s quiet; CONTRIBUTING.md, "Fast or slow")
@pytest.mark.parametrize("mode", ["vmap", "map"])
def test_a_batched_solver_is_read_back_in_the_next_process_instead_of_traced(tmp_path, monkeypatch, mode) -> None:
    """A batched fit keeps its chunk's solver as the one-motor fit keeps its own (issue 37: a fit of
    many captures traced it in every process): the next process reads it, the fits the same bit
    for bit, and another chunk size is another program."""
    from eol_cal.analysis.fit import batch, cache, solver
    from eol_cal.numerics import exported

    rng = np.random.default_rng(38)
    motors = [synthetic_segments(rng, seg_s=0.05, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0),
                                 k6=rng.uniform(4e-4, 8e-4), phase_k6=rng.uniform(-3, 3))[0] for _ in range(5)]
    spec = fit.FitSpec()
    monkeypatch.setattr(exported, "_DIR", None)  # not the suite's directory of kept programs
    plain = fit.fit_many(motors, spec, mode=mode, chunk=4, threads=0)  # no directory: traced
    monkeypatch.setattr(cache, "_LOADED", {})
    first = fit.fit_many(motors, spec, mode=mode, chunk=4, threads=0, cache_dir=tmp_path)
    assert [p.name.split("-")[1] for p in tmp_path.glob("fit-*.jaxexport")] == [mode]
    traced: list = []
    monkeypatch.setattr(cache, "_LOADED", {})  # a new process: nothing read, nothing traced
    monkeypatch.setattr(solver, "_SOLVERS", {})
    build = solver.build_solver
    for module in (solver, batch):
        monkeypatch.setattr(module, "build_solver", lambda *a: traced.append(a))
    second = fit.fit_many(motors, spec, mode=mode, chunk=4, threads=0, cache_dir=tmp_path)
    assert traced == []
    for module in (solver, batch):
        monkeypatch.setattr(module, "build_solver", build)
    for a, b, c in zip(plain, first, second, strict=True):
        for h in (6, 12, 18):
            for part in ("c", "k"):
                assert a.harmonics[h][part] == b.harmonics[h][part] == c.harmonics[h][part]
        assert a.delay_s == b.delay_s == c.delay_s and a.steps == b.steps == c.steps
    fit.fit_many(motors[:3], spec, mode=mode, chunk=4, threads=0, cache_dir=tmp_path)  # a chunk of 3
    assert len(list(tmp_path.glob("fit-*.jaxexport"))) == 2
