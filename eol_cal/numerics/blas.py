"""One BLAS thread per process unless the user asked for more.

The fits solve small systems (tens to a few hundred unknowns). On a station PC whose cores are
busy (the plant, a Dask worker beside it, another job), a multi-threaded OpenBLAS waits for its
own threads: a 114 x 114 inverse took 0.19 s at load 10 on 2 cores instead of 0.5 ms on one
thread, and the refit fell from ~40 to ~0.2 serials/s (docs/benchmarks.md, "Lot refit
throughput"). Dask workers already get one thread from their environment
(:func:`eol_cal.lot.cluster.worker_environ`); this does the same for the command's own process.
"""

from __future__ import annotations

import os
import sys

#: the variables by which a user sets the BLAS thread count; any of them set: left as it is
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads() -> None:
    """Limit the BLAS libraries of this process, loaded now or later, to one thread, unless one
    of :data:`THREAD_VARIABLES` is set (then the user's count stands)."""
    if any(os.environ.get(v) for v in THREAD_VARIABLES):
        return
    # a BLAS loaded later reads its count when it loads: scipy's wheels bring an OpenBLAS of
    # their own, loaded with scipy.linalg (the fingerprint's Cholesky factors), after this call
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    if "numpy" not in sys.modules:
        # numpy's BLAS reads the variable when it loads too: nothing to import for a command that
        # needs no numpy (``eol-cal --help`` stays quick); MKL's builds read theirs
        os.environ["MKL_NUM_THREADS"] = "1"
        return
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
