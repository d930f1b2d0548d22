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
