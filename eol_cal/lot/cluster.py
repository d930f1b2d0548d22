"""The Dask side of a lot refit (and of ``lot simulate``): the local cluster `eol-cal refit` starts,
and what every worker process does before its first task.

A refit task is ~0.2 s of CPU (read and fit 8 motors of six captures) on a machine of few cores, so
what ``distributed`` does beside the tasks counts. Measured on the 2-core machine of
docs/benchmarks.md ("Lot refit throughput"): the worker's statistical profiler (a thread that
samples the task thread's stack every 10 ms) and the 20 ms to 100 ms monitoring loops of the
scheduler, nannies and workers cost 5 to 10 % of a refit's CPU; :data:`REFIT_CONFIG` switches the
profiler off and slows those loops down, and leaves glibc's malloc trimming as it is in a plain
process (``MALLOC_TRIM_THRESHOLD_`` unset: ~20 % of a refit's CPU). Nothing of the scheduling
changes: a task per batch of motor runs, retries, a nanny that restarts a killed worker.
"""

from __future__ import annotations

import contextlib
import gc
import os
from typing import TYPE_CHECKING
from collections.abc import Iterator

from distributed.diagnostics.plugin import WorkerPlugin

if TYPE_CHECKING:
    from distributed import LocalCluster, Worker

#: ``distributed`` settings of a refit's cluster (``dask.config`` keys). The workers inherit them
#: from their nanny, a restarted worker too, while the cluster runs.
REFIT_CONFIG: dict[str, object] = {
    # a thread per worker that walks the task thread's stack every 10 ms (for the dashboard's
    # profile page, which a batch refit does not show)
    "distributed.worker.profile.enabled": False,
    # the event loops' health checks and resource sampling: default 20 ms and 500 ms
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "1s",
    # worker and nanny memory checks: default 100 ms; a worker over its memory limit is still
    # paused or restarted, a second later at most
    "distributed.worker.memory.monitor-interval": "1s",
    # distributed sets MALLOC_TRIM_THRESHOLD_=65536 in its workers (to give freed memory back to
    # the system soon); glibc then unmaps and faults in again the fit's arrays on every capture:
    # ~20 % more CPU per refit (measured with multiprocessing.Pool workers, with and without it)
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
}


def worker_environ() -> dict[str, str]:
    """The environment variables the nanny of :func:`local_cluster` sets for its workers
    (``distributed.nanny.pre-spawn-environ`` under :data:`REFIT_CONFIG`: one OpenMP/MKL/OpenBLAS
    thread per process; variables of this process's environment take precedence)."""
    import dask
    from distributed import Nanny  # noqa: F401 - loads distributed's configuration defaults

    with dask.config.set(REFIT_CONFIG):
        env = dask.config.get("distributed.nanny.pre-spawn-environ")
    return {k: os.environ.get(k, str(v)) for k, v in env.items() if v is not None}


#: the scheduler's HTTP server (:func:`local_cluster`): loopback only, any free port
SCHEDULER_HTTP = "127.0.0.1:0"


@contextlib.contextmanager
def local_cluster(n_workers: int) -> Iterator[LocalCluster]:
    """A ``distributed.LocalCluster`` on 127.0.0.1 for a refit, closed on exit.

    ``n_workers`` worker processes of one thread each (a fit holds the GIL for much of its
    time: threads in one process would wait for each other), each under a nanny that restarts
    it if it dies; no dashboard; :data:`REFIT_CONFIG` for the cluster's lifetime.

    The scheduler serves HTTP even without a dashboard (health and metrics routes): on
    :data:`SCHEDULER_HTTP`, 127.0.0.1 at a port of the system's choosing, so clusters started side
    by side (two refits, a test suite's workers) do not compete for distributed's default 8787.
    """
    import dask
    from distributed import LocalCluster

    with dask.config.set(REFIT_CONFIG), LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                                     host="127.0.0.1", dashboard_address=None,
                                                     scheduler_kwargs={"dashboard_address": SCHEDULER_HTTP}) as cluster:
        yield cluster


def prepare_fit_process(cache_dir: str | os.PathLike[str] | None) -> None:
    """Make this process ready to fit motors: the firmware estimator's tick loop compiled into
    one kernel (:func:`eol_cal.numerics.xla.configure_xla`, when JAX has not started yet), JAX's
    persistent compile cache switched on in
    ``cache_dir`` (:func:`eol_cal.analysis.fit.cache.enable_compile_cache`; ``None``: off), the
    fit's modules imported, one BLAS thread (:func:`eol_cal.numerics.blas.limit_blas_threads`), and the objects
    they made frozen out of the cyclic garbage
    collector (``gc.freeze``: JAX and the libraries of a fit are ~200 000 objects that a full
    collection would otherwise walk every time; none of them is garbage).

    Every process that refits runs it once before its first motor: `eol-cal refit`'s workers
    (:class:`RefitWorkerSetup`), and the loop and the ``multiprocessing.Pool`` of
    ``bench/bench_refit.py``.
    """
    from eol_cal.analysis.fit.cache import enable_compile_cache
    from eol_cal.numerics.blas import limit_blas_threads
    from eol_cal.numerics.xla import configure_xla

    # before JAX starts in this process: the firmware estimator's tick loop (the firmware frame of
    # every capture) in one kernel, ~3x less CPU per capture; the rows do not change
    # (docs/benchmarks.md, "Lot refit throughput")
    configure_xla()
    enable_compile_cache(cache_dir)
    limit_blas_threads()
    # imported here on purpose: loading them is the work this function does ahead of the tasks
    import jax  # noqa: F401

    import eol_cal.analysis.fit.motors
    import eol_cal.capture.io
    import eol_cal.records.limits  # noqa: F401

    gc.collect()
    gc.freeze()


class RefitWorkerSetup(WorkerPlugin):
    """A ``distributed`` worker plugin (``Client.register_plugin``): runs
    :func:`prepare_fit_process` in every worker, one that joins or restarts later too.

    Parameters
    ----------
    cache_dir : path or None
        The fit's cache directory on the workers' machines (``None``: no cache).
    """

    #: the name ``distributed`` keeps the plugin under (registering again replaces it)
    name = "eol-cal-refit-setup"

    def __init__(self, cache_dir: str | os.PathLike[str] | None = None) -> None:
        self.cache_dir = None if cache_dir is None else str(cache_dir)

    def setup(self, worker: Worker) -> None:
        """Called by ``distributed`` in the worker process before its first task."""
        prepare_fit_process(self.cache_dir)
