"""CPU seconds of one what-if motor (`eol-cal lot simulate`'s: the station's cycle on the loopback
simulators, :func:`eol_cal.station.whatif.simulate_motor`), one worker's motors in a row: the
first pays the compilations, the rest are what a lot's motors cost.

    python bench/bench_whatif_motor.py --motors 5 [--profile bench/eol-default-1rev.toml]

XLA set up as a lot's worker sets it (:func:`eol_cal.numerics.xla.configure_xla`: tick loops in one
kernel). CPU, not wall: the machine is shared. Compare two versions side by side by running this with
``PYTHONPATH`` at each one's checkout, one after the other.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motors", type=int, default=5)
    ap.add_argument("--profile", default=str(ROOT / "bench" / "eol-default-1rev.toml"))
    a = ap.parse_args()
    from eol_cal.numerics.xla import configure_xla

    configure_xla()  # as a lot's worker (eol_cal.lot.cluster.prepare_fit_process) and the CLI
    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.sim.loopback import loopback_station
    from eol_cal.station.whatif import simulate_motor
    from eol_cal.station.whatif_plan import LotPlan

    plan = LotPlan("BENCH", "default", str(ROOT / "fixtures" / "limits.toml"), "EPS-STD", a.motors, profile=a.profile)
    warm = []
    with tempfile.TemporaryDirectory() as d:
        for i in range(a.motors):
            c0, t0 = cpu_s(), time.perf_counter()
            rec = simulate_motor(plan, i, Path(d), loopback_station, default_cache_dir())
            cpu, wall = cpu_s() - c0, time.perf_counter() - t0
            warm += [cpu] if i else []
            steps = ", ".join(f"{s.step} {s.seconds:.1f}" for s in rec.steps)
            print(f"motor {i}: {cpu:.1f} s CPU, {wall:.1f} s wall ({steps} s wall), verdict {rec.verdict}, "
                  f"load {os.getloadavg()[0]:.1f}", flush=True)
    if warm:
        print(f"warm motors: {sum(warm) / len(warm):.2f} s CPU a motor over {len(warm)} "
              f"(min {min(warm):.2f}, max {max(warm):.2f})")


if __name__ == "__main__":
    main()
