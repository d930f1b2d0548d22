"""Lot refit throughput: a plain loop, multiprocessing.Pool(2), and Dask distributed with 1 and
2 local worker processes, over the same synthetic lot (one directory of captures per serial).

    python bench/bench_refit.py [--serials 400] [--rounds 2]

All four run the same task (:func:`eol_cal.lot.refit.refit_capture`) in processes prepared the
same way (:func:`eol_cal.lot.cluster.prepare_fit_process`: JAX's compile cache, the fit's
modules, ``gc.freeze``), each warm (one fit per process outside the timing). The Dask runs use
the cluster `eol-cal refit` starts (:func:`eol_cal.lot.cluster.local_cluster`); the Pool's processes get the
environment the nanny gives Dask's workers (:func:`eol_cal.lot.cluster.worker_environ`: one
OpenMP/BLAS thread each). The machine is shared: the alternatives run one after the other
in each round, ``--rounds`` times, and the table sums the rounds; ``cpu/serial`` is the CPU time
(user + system) of every process involved (this one, the pool's, the nannies and workers), which
other jobs on the machine move much less than the wall time.
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

POINTS = [(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]


def make_lot(d: Path, n: int) -> list[list[Path]]:
    from eol_cal.capture.io import write_capture
    from eol_cal.capture.synthetic import synthetic_capture

    groups = []
    for i in range(n):
        sd = d / f"S{i:04d}"
        sd.mkdir()
        g = []
        for j, (rpm, iq) in enumerate(POINTS):
            c = synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=100 * i + j, theta_r0=0.7 * j,
                                  k6=0.0006 + 1e-6 * (i % 50), serial=f"S{i:04d}")
            write_capture(c, sd / f"c{j}.mf4")
            g.append(sd / f"c{j}.mf4")
        groups.append(g)
    return groups


def _fit(group: list[Path]) -> float:
    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot.refit import refit_capture

    row = refit_capture(group, bench="none", cache_dir=default_cache_dir())
    if row["error"] is not None:
        raise RuntimeError(row["error"])
    return row["k6"]


def _init(warm: list[Path], ready: Any = None) -> None:
    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot.cluster import prepare_fit_process

    prepare_fit_process(default_cache_dir())
    _fit(warm)
    if ready is not None:
        ready.release()


def _tree_cpu() -> float:
    """CPU seconds (user + system) of this process and all its descendants alive now."""
    import psutil

    me = psutil.Process()
    total = 0.0
    for p in [me, *me.children(recursive=True)]:
        with contextlib.suppress(psutil.Error):
            t = p.cpu_times()
            total += t.user + t.system
    return total


@contextlib.contextmanager
def _environ(env: dict[str, str]) -> Iterator[None]:
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _timed(run: Callable[[], list[float]]) -> tuple[list[float], float, float]:
    c0, t0 = _tree_cpu(), time.perf_counter()
    k6 = run()
    return k6, time.perf_counter() - t0, _tree_cpu() - c0


def run_loop(lot: list[list[Path]], warm: list[Path]) -> tuple[list[float], float, float]:
    _init(warm)
    return _timed(lambda: [_fit(g) for g in lot])


def run_pool(lot: list[list[Path]], warm: list[Path]) -> tuple[list[float], float, float]:
    from eol_cal.lot.cluster import worker_environ

    ctx = mp.get_context("spawn")
    ready = ctx.Semaphore(0)
    with _environ(worker_environ()), ctx.Pool(2, initializer=_init, initargs=(warm, ready)) as pool:
        for _ in range(2):  # both processes initialised and warm before the clock
            ready.acquire()
        return _timed(lambda: pool.map(_fit, lot, chunksize=1))


def run_dask(lot: list[list[Path]], warm: list[Path], n: int) -> tuple[list[float], float, float]:
    from distributed import Client, wait

    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot.cluster import RefitWorkerSetup, local_cluster
    from eol_cal.lot.refit import refit_capture, refit_lot

    cache_dir = default_cache_dir()
    with local_cluster(n) as cluster, Client(cluster) as client:
        client.register_plugin(RefitWorkerSetup(cache_dir))
        wait([client.submit(refit_capture, [str(q) for q in warm], bench="none", cache_dir=str(cache_dir), pure=False,
                            workers=[addr], allow_other_workers=False) for addr in client.scheduler_info()["workers"]])

        def go() -> list[float]:
            rows = refit_lot(lot, client, bench="none", cache_dir=cache_dir)
            bad = [r["error"] for r in rows if r["error"]]
            if bad:
                raise RuntimeError(bad[0])
            return [r["k6"] for r in rows]

        return _timed(go)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--serials", type=int, default=400)
    ap.add_argument("--rounds", type=int, default=2, help="the alternatives run in turn, this many times")
    a = ap.parse_args()

    runs: dict[str, Callable[[list[list[Path]], list[Path]], tuple[list[float], float, float]]] = {
        "loop (1 process)": run_loop,
        "multiprocessing.Pool(2)": run_pool,
        "dask, 1 worker": lambda lot, warm: run_dask(lot, warm, 1),
        "dask, 2 workers": lambda lot, warm: run_dask(lot, warm, 2),
    }
    wall = dict.fromkeys(runs, 0.0)
    cpu = dict.fromkeys(runs, 0.0)
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:
        lot = make_lot(Path(d), a.serials + 1)
        warm, lot = lot[0], lot[1:]
        ref = None
        for r in range(a.rounds):
            for name, run in runs.items():
                k6, w, c = run(lot, warm)
                if ref is None:
                    ref = k6
                if k6 != ref:
                    raise RuntimeError(f"{name}: k6 differs from the first run's")
                wall[name] += w
                cpu[name] += c
                print(f"round {r + 1}: {name:<24} {a.serials / w:6.2f} serials/s  load {os.getloadavg()[0]:.2f}",
                      flush=True)
    n = a.serials * a.rounds
    base = wall["loop (1 process)"]
    print(f"{a.serials} serials x {len(POINTS)} captures x {a.rounds} round(s), {mp.cpu_count()} cores, "
          f"load average {load0[0]:.2f} at the start, {os.getloadavg()[0]:.2f} at the end")
    print(f"{'':<26}{'s':>8}{'serials/s':>11}{'vs loop':>9}{'cpu/serial':>12}")
    for k in runs:
        print(f"{k:<26}{wall[k]:>8.1f}{n / wall[k]:>11.2f}{base / wall[k]:>8.2f}x{cpu[k] / n:>11.3f}s")
    d2, pool = wall["dask, 2 workers"], wall["multiprocessing.Pool(2)"]
    print(f"dask 2 workers: {base / d2:.2f}x the loop (target >= 1.7x), {pool / d2:.2f}x the Pool (target >= 0.9x)")


if __name__ == "__main__":
    main()
