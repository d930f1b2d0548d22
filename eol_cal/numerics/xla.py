"""Two process-wide XLA settings: the CPU backend compiles a small-enough ``while`` loop into a
single kernel, and the tick loops of this package (the plant's, the firmware estimator's) are
small enough once the threshold is raised (:func:`configure_xla`); and the backend runs a
program on one thread unless the user asks for more (:func:`start_xla`)."""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections.abc import Mapping

from eol_cal.errors import InputError

#: XLA CPU compiles a while loop into one kernel when the bytes it accesses stay below this
#: backend option (default 1024); above it, every fused kernel of the body is dispatched on its
#: own and the tick's ~80 kernels cost ~4 us per iteration instead of ~0.5 us.
_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
_LOOP_BYTES = 1 << 28


def configure_xla() -> bool:
    """Let XLA compile tick loops (the plant's, the firmware estimator's) into a single kernel
    (about 8x faster on CPU).

    Adds ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=2**28`` to
    ``XLA_FLAGS``. XLA reads its flags once, when JAX's backend starts, so this must run before
    the process's first JAX computation; it returns False (and changes nothing) when that has
    happened already or when ``XLA_FLAGS`` sets backend options of its own. The option applies
    to every ``while`` loop of the process without custom calls (LAPACK, ...): call it from
    entry points that mostly simulate or refit (the CLI, benchmarks, a refit worker:
    :func:`eol_cal.lot.cluster.prepare_fit_process`), the fit's and the station's (`eol-cal fit`,
    `eol-cal run`, `eol-cal station`) and the simulators' (`eol-cal dyno-sim --source plant`, the
    demos' in-process plant: ``cli.common.loop_kernels``), not from library code. The plant's tick
    loops give results within float32 rounding of the default (XLA fuses the body differently: a
    layout-2 plant run's i_qc within 0.02 A, its i_q within 0.05 A rms, the identification the
    same, as tests/test_plant_identifying_loop.py checks); the firmware estimator's scan (the
    fit's frame) gives the same output bit for bit at a tenth of the CPU
    (tests/test_firmware_frame_chunk.py); the fit's solver loops hold LAPACK calls and are left
    as they are.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if _LOOP_OPTION in flags:
        return True
    if "xla_backend_extra_options" in flags:
        return False
    if "jax" in sys.modules:
        try:
            from jax._src import xla_bridge

            if xla_bridge.backends_are_initialized():
                return False
        except (ImportError, AttributeError):
            return False
    os.environ["XLA_FLAGS"] = f"{flags} --xla_backend_extra_options={_LOOP_OPTION}={_LOOP_BYTES}".strip()
    return True


def loop_kernel_on() -> bool:
    """Whether this process's XLA compiles tick loops into one kernel (:func:`configure_xla` set
    its option, or the caller's ``XLA_FLAGS`` did)."""
    return _LOOP_OPTION in os.environ.get("XLA_FLAGS", "")


#: environment variable: how many threads XLA's CPU backend runs a program's operations on
#: (default 1; ``all``: XLA's own choice, one per core the process may use)
THREADS_ENV = "EOL_CAL_XLA_THREADS"
#: the process's threads, one directory each (Linux)
_TASKS = "/proc/self/task"


def xla_threads(environ: Mapping[str, str] | None = None) -> int | None:
    """The XLA CPU thread count asked for by :data:`THREADS_ENV` (``None``: XLA's own choice).

    Raises
    ------
    InputError
        The variable is neither a positive integer nor ``all`` (the message names it).
    """
    env = os.environ if environ is None else environ
    text = env.get(THREADS_ENV, "").strip()
    if not text:
        return 1
    if text == "all":
        return None
    if not text.isdigit() or int(text) < 1:
        raise InputError(None, f"${THREADS_ENV}", f"{text!r} is not a positive number of threads or 'all'")
    return int(text)


def start_xla(threads: int | None = None) -> bool:
    """Start JAX's CPU backend with ``threads`` threads for a program's operations (default
    :func:`xla_threads`: one unless the user asked for more).

    XLA's CPU client sizes its pool by the cores the process may use when the backend starts, and
    offers no option for it. This package's programs are tick loops and small solves: a second
    thread finds no work worth sharing and spins. The identifier's scan of 500 power-ups took
    5.4 CPU s at 2.8 s wall on two threads and 2.5 CPU s at 2.5 s on one (2026-11-30, a 2-core
    machine); on a machine whose other core is busy the spinning thread takes it from others.
    So the calling thread's CPU affinity is narrowed while the backend starts, then every thread
    started meanwhile (the pool's) and the caller get the process's cores back: the pool is one
    thread that the kernel may run on any core.

    Call it before the process's first JAX computation (it imports JAX, ~1 s); returns False and
    changes nothing when the backend has started already, when the count is XLA's own (``all``)
    or not fewer than the cores, or where the platform has no per-thread CPU affinity (not Linux,
    or no ``/proc``).
    """
    if threads is None:
        threads = xla_threads()
    if threads is None or not hasattr(os, "sched_setaffinity") or not os.path.isdir(_TASKS):
        return False
    cpus = sorted(os.sched_getaffinity(0))
    if threads >= len(cpus):
        return False
    from jax._src import xla_bridge  # JAX's own: its public API cannot ask whether a backend started

    if xla_bridge.backends_are_initialized():
        return False
    before = _thread_ids()
    os.sched_setaffinity(0, cpus[:threads])
    try:
        xla_bridge.backends()
    finally:
        for tid in (_thread_ids() - before) | {threading.get_native_id()}:
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setaffinity(tid, cpus)
    return True


def _thread_ids() -> set[int]:
    return {int(name) for name in os.listdir(_TASKS)}
