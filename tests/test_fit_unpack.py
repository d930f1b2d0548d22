"""The fit's unpacking (eol_cal/analysis/fit/motor_fit.py): the amplitude/phase pairs of a fit taken
together give what each pair gave alone, bit for bit (issue 37: the batch's unpacking made cheaper
without changing a digit of a record)."""

import math

import numpy as np

from eol_cal.analysis.fit.model import Z95
from eol_cal.analysis.fit.motor_fit import Estimate, amp_phase, amp_phase_pairs
from eol_cal.numerics.wrap import wrap_pi


def one_pair(a: float, b: float, cov2: np.ndarray) -> Estimate:
    """The delta method of one pair as motor_fit computed it before the pairs were stacked."""
    amp = math.hypot(a, b)
    if amp == 0.0:
        return Estimate(0.0, float("inf"), 0.0, float("inf"))
    g_amp = np.array([a, b]) / amp
    g_ph = g_amp[::-1] * np.array([-1.0, 1.0]) / amp
    var_amp = float(g_amp @ cov2 @ g_amp)
    var_ph = float(g_ph @ cov2 @ g_ph)
    return Estimate(amp, Z95 * math.sqrt(max(var_amp, 0.0)), float(wrap_pi(math.atan2(b, a))), Z95 * math.sqrt(max(var_ph, 0.0)))


def test_pairs_together_bit_for_bit_as_each_alone() -> None:
    rng = np.random.default_rng(3)
    for _ in range(300):
        n = 13  # the delay and six pairs, as a fit of c and k at 6, 12, 18
        M = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-7, 0, n)
        cov = M @ M.T
        p = rng.normal(size=n) * 10.0 ** rng.uniform(-6, 1, n)
        p[3:5] = 0.0 if rng.uniform() < 0.1 else p[3:5]  # a pair at zero now and then
        first = 1 + 2 * np.arange(6)
        pair = np.arange(2)
        got = amp_phase_pairs(p[1:].reshape(-1, 2), cov[first[:, None, None] + pair[None, :, None],
                                                        first[:, None, None] + pair[None, None, :]])
        want = [one_pair(p[i], p[i + 1], cov[i : i + 2, i : i + 2]) for i in first]
        assert got == want  # dataclass equality: every field equal, bit for bit
        assert amp_phase(p[1], p[2], cov[1:3, 1:3]) == want[0]


def test_zero_pair_has_no_interval() -> None:
    e = amp_phase(0.0, 0.0, np.eye(2))
    assert e.value == 0.0 and math.isinf(e.ci95) and math.isinf(e.phase_ci95)


def test_host_arrays_are_device_gets_bits() -> None:
    """fit_many reads the solver's outputs with host_arrays (issue 37: jax.device_get cost ~0.25 ms a
    call): the same values, dtypes and shapes as jax.device_get, bit for bit."""
    import jax

    from eol_cal.analysis.fit.batch import host_arrays

    rng = np.random.default_rng(5)
    x = rng.normal(size=(6, 13)) * 10.0 ** rng.uniform(-9, 3, (6, 13))
    with jax.enable_x64(True):
        # the solver's kinds of leaves: float64 arrays and scalars, an int64 and an int32 scalar
        out = jax.jit(lambda a: {"p": a.sum(axis=0) / 3.0, "jac": a[:, None, :] * a[:, :, None],
                                 "steps": (a[:, 0] > 0).sum(), "result": (a[0, 0] > 0).astype(np.int32),
                                 "ssr_red": (a * a).sum()})(x)
        got, want = host_arrays(out), jax.device_get(out)
    assert got.keys() == want.keys()
    for k in want:
        assert got[k].dtype == want[k].dtype and got[k].shape == want[k].shape
        assert got[k].tobytes() == np.asarray(want[k]).tobytes(), k


def test_solver_file_made_once_is_the_key_s_file(tmp_path) -> None:
    """The solver's file, kept per process (issue 37), is the one its full key names, per directory."""
    from eol_cal.analysis.fit import cache
    from eol_cal.analysis.fit.model import FitSpec
    import jax

    from eol_cal.numerics.exported import entry_path, key_text, sources_digest

    spec = FitSpec(fit_c=False, delay_s=0.0)
    with jax.enable_x64(True):
        key = key_text(cache._EXPORT_TAG, (spec, 6, 1, sources_digest(*cache.SOLVER_MODULES)))
    assert cache.solver_file(tmp_path, spec, 6, 1) == entry_path(tmp_path, "fit", key)
    assert cache.solver_file(str(tmp_path), spec, 6, 1) == cache.solver_file(tmp_path, spec, 6, 1)
    assert cache.solver_file(tmp_path / "b", spec, 6, 1).parent == tmp_path / "b"
    assert cache.solver_file(tmp_path, spec, 7, 1) != cache.solver_file(tmp_path, spec, 6, 1)


def test_an_edited_solver_source_is_another_key(tmp_path, monkeypatch) -> None:
    """The solver's key holds its modules' sources: the entry of the code before an edit is never
    read back for the code after it (a kept directory: the CLI's, the suite's)."""
    from eol_cal.numerics.exported import sources_digest

    (tmp_path / "edited_mod.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    before = sources_digest("edited_mod", "eol_cal.analysis.fit.model")
    (tmp_path / "edited_mod.py").write_text("X = 2\n")
    sources_digest.cache_clear()  # a process reads the sources once; the next one reads the edit
    assert sources_digest("edited_mod", "eol_cal.analysis.fit.model") != before
    assert sources_digest("eol_cal.analysis.fit.model", "edited_mod") != before  # the order is in it
