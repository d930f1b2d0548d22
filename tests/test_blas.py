"""One BLAS thread per eol-cal process unless the user sets a count (eol_cal/numerics/blas.py)."""

from __future__ import annotations

import os
import subprocess
import sys

from eol_cal.numerics.blas import THREAD_VARIABLES

PROBE = (
    "import numpy  # noqa: F401\n"
    "from eol_cal.numerics.blas import limit_blas_threads\n"
    "limit_blas_threads()\n"
    "import scipy.linalg  # noqa: F401 - scipy's own OpenBLAS, loaded after the limit\n"
    "from threadpoolctl import threadpool_info\n"
    "print(max(i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'))\n"
)


def _threads(**env: str) -> int:
    clean = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    out = subprocess.run([sys.executable, "-c", PROBE], env={**clean, **env}, capture_output=True,
                         text=True, check=True, timeout=120)
    return int(out.stdout.strip())


def test_one_blas_thread_by_default():
    assert _threads() == 1


def test_a_count_the_user_set_stands():
    assert _threads(OPENBLAS_NUM_THREADS="2") == 2
