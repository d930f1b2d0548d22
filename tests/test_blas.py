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
    "import numpy  # noqa: F401, F811 - loaded before the limit (above) or after it (the CLI's way)\n"
    "import scipy.linalg  # noqa: F401 - scipy's own OpenBLAS, loaded after the limit\n"
    "from threadpoolctl import threadpool_info\n"
    "print(max(i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'))\n"
)


def _threads(numpy_first: bool = True, **env: str) -> int:
    clean = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    probe = PROBE if numpy_first else PROBE.split("\n", 1)[1]
    out = subprocess.run([sys.executable, "-c", probe], env={**clean, **env}, capture_output=True,
                         text=True, check=True, timeout=120)
    return int(out.stdout.strip())


def test_one_blas_thread_by_default():
    assert _threads() == 1


def test_one_blas_thread_when_numpy_loads_after_the_limit():
    """The CLI limits before anything imports numpy (and imports none for it: ``--help``)."""
    assert _threads(numpy_first=False) == 1
    clean = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    out = subprocess.run([sys.executable, "-c", "import sys\nfrom eol_cal.numerics.blas import limit_blas_threads\n"
                          "limit_blas_threads()\nprint('numpy' in sys.modules)"], env=clean, capture_output=True,
                         text=True, check=True, timeout=120)
    assert out.stdout.strip() == "False"


def test_a_count_the_user_set_stands():
    assert _threads(OPENBLAS_NUM_THREADS="2") == 2
