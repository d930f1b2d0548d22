"""Lot refit throughput: a plain loop, multiprocessing.Pool(2), and Dask distributed with 1 and
2 local worker processes, over the same synthetic lot (one directory of captures per serial).

    python bench/bench_refit.py [--serials 400]

Every process turns on the JAX persistent compile cache first (as `eol-cal refit`'s workers do)
and fits one warm-up motor outside the timing, so the figures are the steady fitting rate.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import tempfile
import time
from pathlib import Path

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


def _init() -> None:
    from eol_cal.analysis.fit.cache import default_cache_dir, enable_compile_cache

    enable_compile_cache(default_cache_dir())


def _fit(group: list[Path]) -> float:
    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot.refit import refit_capture

    row = refit_capture(group, bench="none", cache_dir=default_cache_dir())
    assert row["error"] is None, row["error"]
    return row["k6"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--serials", type=int, default=400)
    a = ap.parse_args()
    from distributed import Client, LocalCluster

    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot.refit import refit_lot

    with tempfile.TemporaryDirectory() as d:
        lot = make_lot(Path(d), a.serials + 1)
        warm, lot = lot[0], lot[1:]
        out = {}
        _init()
        _fit(warm)
        t0 = time.perf_counter()
        ref = [_fit(g) for g in lot]
        out["loop (1 process)"] = time.perf_counter() - t0
        with mp.get_context("spawn").Pool(2, initializer=_init) as pool:
            pool.map(_fit, [warm, warm])
            t0 = time.perf_counter()
            got = pool.map(_fit, lot, chunksize=1)
            out["multiprocessing.Pool(2)"] = time.perf_counter() - t0
        assert got == ref
        for n in (1, 2):
            with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                              dashboard_address=None, silence_logs=50) as cluster, Client(cluster) as client:
                client.register_worker_callbacks(_init)
                refit_lot([warm] * n, client, bench="none", cache_dir=default_cache_dir())
                t0 = time.perf_counter()
                rows = refit_lot(lot, client, bench="none", cache_dir=default_cache_dir())
                out[f"dask, {n} worker(s)"] = time.perf_counter() - t0
            assert [r["k6"] for r in rows] == ref
    base = out["loop (1 process)"]
    print(f"{a.serials} serials x {len(POINTS)} captures, {mp.cpu_count()} cores")
    print(f"{'':<26}{'s':>8}{'serials/s':>11}{'vs loop':>9}")
    for k, v in out.items():
        print(f"{k:<26}{v:>8.1f}{a.serials / v:>11.2f}{base / v:>8.2f}x")


if __name__ == "__main__":
    main()
