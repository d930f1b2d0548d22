"""`eol-cal lot simulate` on 2 cores: wall time of a lot, 2 workers against 1, and its predicted
yield and compensated p-p against the 100-motor `bench/bench_fit_lot.py` result.

    python bench/bench_fit_lot.py --motors 100 --estimator best --no-nominal-halls --no-effective --json fitlot.json
    python bench/bench_lot_simulate.py --motors 1000 --fit-lot fitlot.json [--profile FILE] [--scaling 160]

The lot runs as the command runs it (:func:`eol_cal.station.whatif.simulate_lot` on the local
cluster `eol-cal lot simulate` starts, records into a new SQLite file), with the limits of
``fixtures/limits.toml`` (variant EPS-STD) but ``max_pp_after_pct = 1.0``: bench_fit_lot's
compensated p-p target, so the lot's yield and the fraction of bench_fit_lot's motors within
1.0 % are the same figure. bench_fit_lot's 95 % intervals: Wilson's for its fraction within
1.0 %, the order statistics' for its median. ``--scaling N``: N motors with 1 and then 2 workers
(alternated twice), the speed-up of the second.

    python bench/bench_lot_simulate.py --per-motor 4 --profile bench/eol-default-1rev.toml

``--per-motor N``: CPU seconds a warm motor costs in one process (set up as a lot's worker,
:func:`eol_cal.lot.cluster.prepare_fit_process`): the production cycle on the plant in-process
(:func:`eol_cal.station.whatif.simulate_motor` with
:func:`eol_cal.sim.plant_instruments.plant_instruments`), N motors one after the other, then N
motors as a lot's batch runs them (:func:`eol_cal.station.whatif.simulate_batch`: in threads),
after one motor that pays the compilations; and each step's CPU seconds (the process's, every
thread's, between the executor's events) of the motors one after the other. CPU, not wall: the
machine is shared. (At 12078a8 it ran the batched steps beside it: 4.18 s against 4.33 s CPU a
motor.)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def run_lot(db: Path, name: str, motors: int, workers: int, limits: Path, profile: str, seed: int = 0) -> float:
    from distributed import Client

    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot.cluster import RefitWorkerSetup, local_cluster
    from eol_cal.sim.plant_instruments import plant_instruments
    from eol_cal.station.whatif import simulate_lot
    from eol_cal.station.whatif_plan import LotPlan

    plan = LotPlan(name, "default", str(limits), "EPS-STD", motors, seed=seed, profile=profile)
    t0 = time.perf_counter()
    with local_cluster(workers) as cluster, Client(cluster) as client:
        client.register_plugin(RefitWorkerSetup(default_cache_dir()))
        out = simulate_lot(plan, db, client, plant_instruments, cache_dir=default_cache_dir())
    if out.failed_batches:
        raise RuntimeError(out.failed_batches[0][1])
    return time.perf_counter() - t0


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def per_motor(motors: int, limits: Path, profile: str, work: Path) -> None:
    """``--per-motor``: the CPU seconds of a warm motor, one after the other and in a batch's
    threads, and per step (module doc)."""
    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot.cluster import prepare_fit_process

    prepare_fit_process(default_cache_dir())  # as a lot's worker
    from eol_cal.sim.plant_instruments import plant_instruments
    from eol_cal.station.executor import StepEvent
    from eol_cal.station.whatif import MOTOR_THREADS, simulate_batch, simulate_motor
    from eol_cal.station.whatif_plan import LotPlan

    plan = LotPlan("PM", "default", str(limits), "EPS-STD", 2 * motors + 1, seed=0, profile=profile, batch=motors)
    cache = default_cache_dir()
    simulate_motor(plan, 0, work / "m0", plant_instruments, cache)
    steps: dict[str, float] = {}
    started = [0.0]

    def step_cpu(e: StepEvent) -> None:  # one motor at a time: the process's CPU is this step's
        if e.what == "start":
            started[0] = cpu_s()
        else:
            steps[e.step] = steps.get(e.step, 0.0) + cpu_s() - started[0]

    c0, t0 = cpu_s(), time.perf_counter()
    cycled = [simulate_motor(plan, i, work / f"m{i}", plant_instruments, cache, observers=[step_cpu])
              for i in range(1, motors + 1)]
    cpu, wall = (cpu_s() - c0) / motors, (time.perf_counter() - t0) / motors
    print(f"{motors} warm motors, profile {profile}: the production cycle on the plant in-process, one after the "
          f"other: {cpu:.2f} s CPU a motor ({wall:.2f} s wall); verdicts {[r.verdict for r in cycled]}; "
          f"load {os.getloadavg()[0]:.2f}", flush=True)
    print("  CPU s a motor by step: " + ", ".join(f"{k} {v / motors:.3f}" for k, v in steps.items()), flush=True)
    c0, t0 = cpu_s(), time.perf_counter()
    docs = simulate_batch(plan, range(motors + 1, 2 * motors + 1), plant_instruments, str(cache))
    cpu, wall = (cpu_s() - c0) / motors, (time.perf_counter() - t0) / motors
    print(f"  as a batch of {motors} ({MOTOR_THREADS} at a time, in threads): {cpu:.2f} s CPU a motor "
          f"({wall:.2f} s wall); verdicts {[d['verdict'] for d in docs]}; load {os.getloadavg()[0]:.2f}", flush=True)


def intervals(pp: np.ndarray) -> dict[str, tuple[float, float, float]]:
    """bench_fit_lot's fraction within 1.0 % and median, each with its 95 % interval."""
    from scipy import stats

    n, k = len(pp), int(np.count_nonzero(pp <= 1.0))
    z, p = 1.959964, k / n
    den = 1 + z * z / n
    c, h = (p + z * z / (2 * n)) / den, z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    s = np.sort(pp)
    lo, hi = int(stats.binom.ppf(0.025, n, 0.5)), int(stats.binom.isf(0.025, n, 0.5))
    return {"yield": (p, c - h, c + h), "median": (float(np.median(pp)), float(s[lo - 1]), float(s[hi]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motors", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--profile", default="eol-default")
    ap.add_argument("--fit-lot", type=Path, default=None, help="bench_fit_lot.py --json rows to compare with")
    ap.add_argument("--scaling", type=int, default=0, help="motors of the 1-against-2-workers runs (0: none)")
    ap.add_argument("--per-motor", type=int, default=0, help="CPU s of a warm motor, alone and in a batch's threads (module doc)")
    a = ap.parse_args()
    from eol_cal.records.query import query_records

    with tempfile.TemporaryDirectory() as d:
        limits = Path(d) / "limits.toml"
        limits.write_text((ROOT / "fixtures" / "limits.toml").read_text().replace(
            "max_pp_after_pct = 2.0", "max_pp_after_pct = 1.0", 1))
        if a.per_motor:
            per_motor(a.per_motor, limits, a.profile, Path(d))
            return
        load0 = os.getloadavg()[0]
        db = Path(d) / "lot.sqlite"
        wall = run_lot(db, "LOT", a.motors, a.workers, limits, a.profile)
        print(f"{a.motors} motors, {a.workers} workers, profile {a.profile}: {wall:.0f} s "
              f"({wall / 60:.1f} min; target <= 10 min); load average {load0:.2f} at the start, "
              f"{os.getloadavg()[0]:.2f} at the end", flush=True)
        recs = query_records(db, kind="simulated")
        pp = np.array([r.value("pp_after_pct") for r in recs])
        verdicts = {v: sum(r.verdict == v for r in recs) for v in ("pass", "fail", "error")}
        judged = verdicts["pass"] + verdicts["fail"]
        print(f"predicted yield {verdicts['pass'] / judged:.3f} ({verdicts}); compensated p-p median "
              f"{np.nanmedian(pp):.3f} %, p95 {np.nanpercentile(pp, 95):.3f} %, within 1.0 %: "
              f"{int(np.count_nonzero(pp <= 1.0))}/{len(pp)}")
        if a.fit_lot is not None:
            rows = json.loads(a.fit_lot.read_text())
            ref = intervals(np.array([r["pp_after_pct"] for r in rows if r.get("estimator", "best") == "best"], float))
            y, m = ref["yield"], ref["median"]
            ours_y, ours_m = verdicts["pass"] / judged, float(np.nanmedian(pp))
            print(f"bench_fit_lot ({len(rows)} motors): within 1.0 % {y[0]:.3f} [95 % {y[1]:.3f}, {y[2]:.3f}] -> "
                  f"lot {'inside' if y[1] <= ours_y <= y[2] else 'OUTSIDE'}; median {m[0]:.3f} % [{m[1]:.3f}, {m[2]:.3f}] "
                  f"-> lot {'inside' if m[1] <= ours_m <= m[2] else 'OUTSIDE'}")
        for r in range(2 if a.scaling else 0):
            t = {}
            for w in (1, 2):
                t[w] = run_lot(Path(d) / f"s{r}{w}.sqlite", f"S{r}{w}", a.scaling, w, limits, a.profile, seed=10_000)
            print(f"scaling round {r + 1}: {a.scaling} motors, 1 worker {t[1]:.0f} s, 2 workers {t[2]:.0f} s: "
                  f"{t[1] / t[2]:.2f}x (target >= 1.8x); load {os.getloadavg()[0]:.2f}", flush=True)


if __name__ == "__main__":
    main()
