"""scipy's LAPACK without the package ``scipy.linalg``'s import (eol_cal/numerics/lapack.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np


def _run(code: str, *args: str) -> dict:
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_flapack_is_scipys_lapack_loaded_without_the_package():
    code = """if True:
        import json, sys
        import numpy as np
        from eol_cal.numerics.lapack import flapack
        lapack = flapack()
        alone = "scipy.linalg" in sys.modules
        G = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
        L, info = lapack.dpotrf(G, lower=1)
        import scipy.linalg, scipy.linalg.lapack
        from scipy.linalg import _flapack
        same = (scipy.linalg.lapack.dpotrf is lapack.dpotrf and scipy.linalg.lapack.dtrtrs is lapack.dtrtrs
                and _flapack is lapack and flapack() is lapack)
        bits = (scipy.linalg.cholesky(G, lower=True) == np.tril(L)).all()
        print(json.dumps({"linalg_before": alone, "info": info, "same": same, "bits": bool(bits)}))
    """
    got = _run(code)
    assert got == {"linalg_before": False, "info": 0, "same": True, "bits": True}


def test_the_fingerprints_inverse_is_scipys_cho_solve_bit_for_bit():
    from scipy.linalg import cho_solve

    from eol_cal.analysis.fingerprint_fit import _cho_inverse
    from eol_cal.numerics.lapack import flapack

    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 40))
    G = A @ A.T + 40 * np.eye(40)
    L = np.linalg.cholesky(G)
    assert np.array_equal(_cho_inverse(flapack(), L), cho_solve((L, True), np.eye(40), check_finite=False))


def test_a_kept_program_with_lapack_runs_in_the_next_process_without_scipy_linalg(tmp_path):
    """The second process reads the exported program back; jax initialises LAPACK for it from the
    preloaded pointer modules, and its answer is the first process's, bit for bit."""
    code = """if True:
        import json, sys
        import numpy as np
        import jax, jax.numpy as jnp
        jax.config.update("jax_enable_x64", True)
        from eol_cal.numerics import exported
        exported.set_cache_dir(sys.argv[1])
        A = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
        b = np.array([1.0, -2.0, 0.5])
        f = exported.kept("t-solve", "test-1", None, lambda: jax.jit(jnp.linalg.solve), (A, b))
        x = np.asarray(f(A, b))
        print(json.dumps({"x": x.tolist(), "linalg": "scipy.linalg" in sys.modules,
                          "pointers": "scipy.linalg.cython_lapack" in sys.modules}))
    """
    first = _run(code, str(tmp_path))
    second = _run(code, str(tmp_path))
    assert any(tmp_path.iterdir())  # the program was kept
    assert second["x"] == first["x"]
    np.testing.assert_allclose(second["x"], np.linalg.solve([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]],
                                                            [1.0, -2.0, 0.5]), rtol=1e-12)
    assert second["pointers"] and not second["linalg"]
