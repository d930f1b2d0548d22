"""Fitting one motor or many: compression in numpy, the nonlinear solve batched in JAX."""

from __future__ import annotations

import contextvars
import dataclasses
import os
from collections.abc import Callable, Generator
from typing import Any
import threading
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from eol_cal.analysis.fit.cache import load_solver, save_solver
from eol_cal.analysis.fit.compress_process import PROCESS_MIN_MOTORS, PROCESS_START_MOTORS, SLOTS, compress_process, running
from eol_cal.analysis.fit.compression import (COMPRESSED_KEYS, Compressed, Summarise, compress_many, compressed_dict,
                                              summarise_segments)
from eol_cal.analysis.fit.model import FitSpec, SteadySegments, check_identifiable
from eol_cal.analysis.fit.motor_fit import MotorFit, segment_coefficients, unpack
from eol_cal.analysis.fit.solver import build_solver, cached_solver, mode_solver, tau_grid
from eol_cal.numerics.exported import cache_dir as process_cache_dir


def fit_segments(seg: SteadySegments, spec: FitSpec = FitSpec(), source: str | None = None,
                 cache_dir: str | os.PathLike[str] | None = None) -> MotorFit:
    """Fit one motor from its segments (all captures jointly).

    Parameters
    ----------
    seg : SteadySegments
        Electrical angle (rad), time (s), torque (N*m) per segment, with i_qo (A) and omega_e (rad/s).
    spec : FitSpec
        Model and solver settings.
    source : str, optional
        Named in errors.
    cache_dir : path, optional
        Directory of serialized solvers (:mod:`eol_cal.analysis.fit.cache`); ``None``: as :func:`fit_many`.

    Returns
    -------
    MotorFit
    """
    return fit_many([seg], spec, mode="loop", sources=[source], cache_dir=cache_dir)[0]


#: ``fit_many(mode="auto")`` batches the solve from this many motors on (below, the compile of a
#: batched program costs more than the per-call dispatch it saves)
AUTO_BATCH_MIN = 16


def pick_mode(n_motors: int) -> str:
    """The batch mode ``fit_many(mode="auto")`` uses for ``n_motors``: ``loop`` or ``vmap``.

    ``vmap``: its solve took 0.125-0.138 ms CPU a capture against ``map``'s 0.159-0.169 (median of
    five each, chunks of 16, 64 and 100 captures, 2 cores, load 3.2; issue 37), the fits the same
    to 2e-12 relative (tests/test_fit_batch_mode.py holds them to the batch's 1e-9). It runs every
    member of a chunk until the slowest has converged, but from the closed-form start all take
    6-9 steps, and a member that has converged is held where it is, so its result does not move.
    """
    return "vmap" if n_motors >= AUTO_BATCH_MIN else "loop"


def fit_many(
    motors: list[SteadySegments],
    spec: FitSpec = FitSpec(),
    mode: str = "auto",
    chunk: int = 64,
    sources: list[str | None] | None = None,
    progress: Callable[[int], None] | None = None,
    threads: int | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
    process: bool | None = None,
) -> list[MotorFit]:
    """Fit many motors: compression in numpy, the nonlinear solve batched in JAX.

    With ``threads`` > 0 worker threads compress the motors ahead, block after block, while this
    thread unpacks the last chunk's results (XLA solves the next chunk meanwhile on its own
    threads; XLA and the numpy kernels release the GIL) and compresses too rather than wait.

    Parameters
    ----------
    motors : list of SteadySegments
        One entry per motor.
    spec : FitSpec
        Shared model and solver settings.
    mode : {"loop", "vmap", "map", "auto"}
        ``loop``: one jitted solve per motor; ``vmap``: one vectorised solve per chunk (every member
        iterates until the slowest has converged); ``map``: ``jax.lax.map`` inside one jitted call;
        ``auto``: :func:`pick_mode`.
    chunk : int
        Motors per batched call (vmap/map); also the progress granularity.
    sources : list, optional
        Per motor, named in errors.
    progress : callable, optional
        Called with the number of motors finished after each chunk.
    threads : int, optional
        Worker threads that compress ahead of the solve, :data:`COMPRESS_BLOCK` motors at a time
        (their columns built by a few long numpy kernels and their products by BLAS called without
        the GIL, :func:`~eol_cal.numerics.gemm.gram_halves`: a compression thread holds the GIL
        about a quarter of its time, between kernels), or hand them to the compression process
        (``process``) and wait; this thread compresses beside them whenever it would wait for them.
        0 compresses in this thread alone. ``None`` (default): with the process, two (one block
        copied in while it compresses another); else :func:`compression_threads`, one worker for a
        batch of 32 motors or more on a machine of two cores or more, which with this thread keeps
        both cores of a 2-core machine busy (docs/benchmarks.md).
    cache_dir : path, optional
        Directory of serialized solvers (:mod:`eol_cal.analysis.fit.cache`, usually
        :func:`~eol_cal.analysis.fit.cache.default_cache_dir`): the solver of the mode (one motor's,
        or a chunk's of the chunk's size) is read from there instead of traced, or written there
        after tracing. ``None``: the process's
        directory of exported programs (:func:`eol_cal.numerics.exported.cache_dir`, which
        :func:`~eol_cal.analysis.fit.cache.enable_compile_cache` sets), none where it is unset.
    process : bool, optional
        The worker threads hand their blocks to a second process
        (:mod:`~eol_cal.analysis.fit.compress_process`: its own GIL; started on first use, kept for
        this process' life) instead of compressing them here. ``None`` (default): where there is a
        worker thread, for a batch of
        :data:`~eol_cal.analysis.fit.compress_process.PROCESS_START_MOTORS` motors or more, or of
        :data:`~eol_cal.analysis.fit.compress_process.PROCESS_MIN_MOTORS` or more once the process
        runs. Where it cannot start, the workers compress here. The fits are the same bit for bit.

    Returns
    -------
    list of MotorFit
    """
    import jax

    if mode == "auto":
        mode = pick_mode(len(motors))
    if cache_dir is None:
        cache_dir = process_cache_dir()
    sources = sources or [None] * len(motors)
    for seg, src in zip(motors, sources, strict=True):
        check_identifiable(seg, spec, src)
    S = max(m.n_segments for m in motors)
    omega_max = max(float(np.abs(m.omega_e).max()) for m in motors)
    grid = tau_grid(spec, omega_max)
    results: list[MotorFit] = []
    workers = compression_threads(len(motors)) if threads is None else threads
    summarise = _worker_summarise(workers > 0 and len(motors) > 1, len(motors), process)
    if threads is None:
        # feeding the process, a worker waits for it: one a request it takes at once (its SLOTS)
        threads = workers if summarise is summarise_segments else SLOTS
    pool = ThreadPoolExecutor(max_workers=threads) if threads > 0 and len(motors) > 1 else None
    comps_in_order = None
    try:
        comps_in_order = _compressions(motors, spec, S, min(chunk, COMPRESS_BLOCK), pool, threads, summarise,
                                       sources)
        with jax.enable_x64(True):
            # numpy in (float64): a jax.numpy.asarray here is a program of its own to look up
            grid_j = np.asarray(grid, dtype=np.float64)
            # a known delay reaches the solver in the grid: one program for every delay
            program = spec if spec.fit_delay else dataclasses.replace(spec, delay_s=0.0)
            # a chunk's motors: the chunk size, or every motor where they are fewer (one compiled shape)
            batch = None if mode == "loop" else (mode, chunk if len(motors) > chunk else len(motors))
            exported = load_solver(cache_dir, program, S, len(grid), batch)
            solve = _taking_steps(exported) if exported else cached_solver(program, S, "one" if mode == "loop" else mode)
            save_export = exported is None and cache_dir is not None
            step = 1 if mode == "loop" else chunk
            # one solve in flight: the next chunk's is dispatched (XLA runs it on its own threads)
            # before this thread unpacks the last one's results, so the two overlap
            pending: tuple[list[SteadySegments], list[Compressed], dict | None, Any] | None = None
            for start in range(0, len(motors), step):
                block = motors[start : start + step]
                comps = [next(comps_in_order) for _ in block]
                if mode == "loop":
                    comp, stacked = compressed_dict(comps[0]), None
                else:
                    # pad the last chunk to the chunk size: one compiled shape
                    padded = comps + [comps[-1]] * (chunk - len(comps)) if len(motors) > chunk else comps
                    comp = stacked = {k: np.stack([getattr(c, k) for c in padded]) for k in COMPRESSED_KEYS}
                args = (comp, grid_j)
                if save_export:
                    save_export = False
                    save_solver(cache_dir, jax.jit(_solver_program(program, S, mode, spec.max_steps)), program, S,
                                len(grid), args, batch)
                    # the solver read back, not the traced one, compiled and used from the first
                    # motor on: the next process compiles nothing (the persistent compilation
                    # cache holds this program), and every motor gets the same program
                    exported = load_solver(cache_dir, program, S, len(grid), batch)
                    if exported:
                        solve = _taking_steps(exported)
                out = solve(comp, grid_j, spec.max_steps)
                if pending:
                    _unpack_into(results, *pending, spec, progress)
                pending = (block, comps, stacked, out)
            if pending:
                _unpack_into(results, *pending, spec, progress)
    finally:
        if comps_in_order is not None:
            comps_in_order.close()  # its workers take no further block (an error here: they would compress them all)
        if pool:
            pool.shutdown(cancel_futures=True)
    return results


def _unpack_into(results: list[MotorFit], block: list[SteadySegments], comps: list[Compressed], batch: dict | None,
                 out: Any, spec: FitSpec, progress: Callable[[int], None] | None) -> None:
    """Append the fits of ``block`` to ``results`` from their solve's output ``out`` (one motor's
    with ``batch`` None, else the chunk's, whose input was ``batch``), fetched from XLA here: it
    waits for the solve. A chunk's segment coefficients are made for all its motors at once."""
    got = host_arrays(out)
    if batch is None:
        results.append(unpack(got, comps[0], spec, block[0].n_segments))
    else:
        B, (S, m) = len(block), batch["R"].shape[1:3]
        t_avg, coef = segment_coefficients(batch["R"][:B].reshape(B * S, m, m), batch["z"][:B].reshape(B * S, m),
                                           got["g"][:B].reshape(B * S, -1), np.concatenate([c.ymean for c in comps]),
                                           spec.n_nuis)
        t_avg, coef = t_avg.reshape(B, S), coef.reshape(B, S, m)
        for j, (mot, c) in enumerate(zip(block, comps, strict=True)):
            n = mot.n_segments
            results.append(unpack({k: v[j] for k, v in got.items()}, c, spec, n, (t_avg[j, :n], coef[j, :n])))
    if progress:
        progress(len(results))


def host_arrays(out: dict[str, Any]) -> dict[str, np.ndarray]:
    """The solver's outputs as numpy arrays (the same values: the host buffers XLA wrote on the CPU,
    read-only views), waiting for the solve. ``jax.device_get`` gives the same arrays at ~0.25 ms
    more CPU a call (its tree walk and an asynchronous copy started per leaf: ~30 us for each of the
    eight leaves; three calls a refit's serial, issue 37)."""
    return {k: np.asarray(v) for k, v in out.items()}


def compression_threads(n_motors: int) -> int:
    """The compression's worker threads ``fit_many(threads=None)`` uses for ``n_motors``: 1 from two
    :data:`COMPRESS_BLOCK` s of motors on where this process may run on two cores or more, else 0.

    One, not two: the calling thread compresses too whenever it would wait (:func:`_compressions`),
    so one worker beside it keeps two cores busy (the solve runs on XLA's threads), and a second
    worker only adds a third thread taking turns at the GIL: 0.1-0.2 ms more CPU a capture
    (docs/benchmarks.md)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 1 if cores >= 2 and n_motors >= 2 * COMPRESS_BLOCK else 0


#: motors compressed together (:func:`~eol_cal.analysis.fit.compression.compress_many`): their
#: columns built side by side, one unit of work of the compression's threads
COMPRESS_BLOCK = 16


def _worker_summarise(workers: bool, n_motors: int, process: bool | None) -> Summarise:
    """What the compression's worker threads summarise segments with: the second process's
    :meth:`~eol_cal.analysis.fit.compress_process.CompressProcess.summarise` where ``process`` (or,
    None, a batch of ``PROCESS_START_MOTORS`` or more, or ``PROCESS_MIN_MOTORS`` once it runs) asks
    for it and it runs, else in this process."""
    if not workers or process is False:
        return summarise_segments
    if process is None and n_motors < (PROCESS_MIN_MOTORS if running() else PROCESS_START_MOTORS):
        return summarise_segments
    child = compress_process()
    return child.summarise if child else summarise_segments


def _compressions(motors: list[SteadySegments], spec: FitSpec, S: int, block: int,
                  pool: ThreadPoolExecutor | None, workers: int, summarise: Summarise = summarise_segments,
                  sources: list[str | None] | None = None) -> Generator[Compressed, None, None]:
    """Each motor's compression, in order, ``block`` motors at a time: in this thread, or also on
    ``pool``'s ``workers`` threads, which take the blocks in order and run ahead of the solve (a few kB of
    result a motor). This thread compresses too rather than wait: the block it needs if no worker
    has taken it, else the next free ones until the worker's is done. One worker beside it keeps
    two cores busy with fewer threads taking turns at the GIL than two workers beside a waiting one.
    The workers summarise with ``summarise`` (another process's), this thread here. An error names
    its capture (``sources``, else its index)."""
    starts = list(range(0, len(motors), block))

    def run(i: int, how: Summarise = summarise_segments) -> list[Compressed]:
        try:
            return compress_many(motors[starts[i] : starts[i] + block], spec, S, how)
        except Exception as e:
            _name_capture(e, motors, starts[i], block, spec, S, sources)
            raise

    if pool is None:
        for i in range(len(starts)):
            yield from run(i)
        return
    claims = _Claims(len(starts))
    done: list[Future[list[Compressed]]] = [Future() for _ in starts]

    def work() -> None:
        while (i := claims.next()) is not None:
            _settle(done[i], lambda i: run(i, summarise), i)

    # each in this thread's context: a shared_compression scope's segments are shared with the workers
    for _ in range(workers):
        pool.submit(contextvars.copy_context().run, work)
    try:
        for i, f in enumerate(done):
            if claims.take(i):
                _settle(f, run, i)
            # a worker holds it: the next free block compressed here meanwhile, rather than waiting
            while not f.done() and (j := claims.next()) is not None:
                _settle(done[j], run, j)
            yield from f.result()
    finally:
        claims.close()  # the workers take no further block (an error, or the caller stopped early)


class _Claims:
    """Which blocks have been taken, under a lock: the workers take the first free one in order
    (:meth:`next`), the consuming thread the one it needs (:meth:`take`)."""

    def __init__(self, n: int) -> None:
        self._free = [True] * n
        self._cursor = 0
        self._lock = threading.Lock()

    def next(self) -> int | None:
        """The first block not yet taken, now taken; None when none is left (or after :meth:`close`)."""
        with self._lock:
            while self._cursor < len(self._free) and not self._free[self._cursor]:
                self._cursor += 1
            if self._cursor == len(self._free):
                return None
            self._free[self._cursor] = False
            return self._cursor

    def take(self, i: int) -> bool:
        """Take block ``i`` if no one has: True if the caller now has it."""
        with self._lock:
            free, self._free[i] = self._free[i], False
            return free

    def close(self) -> None:
        """Take every block left: the workers stop after the one they hold."""
        with self._lock:
            self._free = [False] * len(self._free)


def _settle(f: Future[list[Compressed]], run: Callable[[int], list[Compressed]], i: int) -> None:
    """``f`` set to ``run(i)``, or to the error it raised."""
    try:
        f.set_result(run(i))
    except Exception as e:  # noqa: BLE001 - handed to the consumer, which raises it (as a worker's future did)
        f.set_exception(e)


def _name_capture(e: Exception, motors: list[SteadySegments], first: int, block: int, spec: FitSpec, S: int,
                  sources: list[str | None] | None) -> None:
    """A note on ``e``, the error of the block of ``motors`` from ``first``, naming the capture that
    raises it compressed alone here (the first of the block's that does), else the block's."""
    names = [sources[j] if sources and sources[j] else f"#{j}" for j in range(len(motors))]
    for j in range(first, min(first + block, len(motors))):
        try:
            compress_many([motors[j]], spec, S)
        except Exception:  # noqa: BLE001 - the capture found; the block's error is raised
            e.add_note(f"in the compression of capture {names[j]}")
            return
    e.add_note(f"in the compression of captures {names[first]} to {names[min(first + block, len(motors)) - 1]}")


def _solver_program(spec: FitSpec, S: int, mode: str, steps: int) -> Callable:
    """The solver of ``mode`` (:func:`fit_many`'s: one motor, or a chunk's by ``vmap`` or
    ``jax.lax.map``: :func:`~eol_cal.analysis.fit.solver.mode_solver`) as
    ``(compressed, tau_grid) -> outputs``, ``steps`` its step limit: what is exported
    (:func:`~eol_cal.analysis.fit.cache.save_solver`)."""
    solve = mode_solver(build_solver(spec, S), "one" if mode == "loop" else mode)
    return lambda c, g: solve(c, g, steps)


def _taking_steps(exported: Callable) -> Callable:
    """A deserialized solver ``(compressed, grid)`` called as the jitted ones are, with the step
    limit (a constant of the exported program, part of its key: ignored)."""
    return lambda comp, grid, _steps: exported(comp, grid)
