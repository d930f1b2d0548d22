"""XLA's CPU pool: one thread (`eol-cal`'s default, :func:`eol_cal.numerics.xla.start_xla`) against
XLA's own choice (one thread a core: ``EOL_CAL_XLA_THREADS=all``), on the package's JAX work.

Each alternative runs in a fresh process of its own, alternated ``--rounds`` times, and times
one workload after a warm-up call (compiling is not counted):

- ``identifier``: the firmware identifier's scan over 500 power-ups at 100-200 rpm, 2 s of 20 kHz
  ticks (:func:`eol_cal.firmware.mech_sim.simulate_powerups`, drawn as ``bench/bench_mech_id.py``
  draws a band);
- ``plant``: the built-in plant, one motor (the paper's), 30 s at 120 rpm and 20 A, compensated
  with its true layout-2 block, every estimator option (:func:`eol_cal.plant.simulate.simulate`).

Printed per alternative: wall s, CPU s (user + system, every thread), cores (CPU over wall), and
the pool's threads (XLA names them ``tf_XLAEigen``). The results of both are compared (equal, or
the largest difference).

    python bench/bench_xla_threads.py [--rounds 2] [--work identifier,plant]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
ALTERNATIVES = {"one thread (eol-cal's default)": "1", "XLA's own (one a core)": "all"}


def _pool_threads() -> int:
    return sum(open(f"/proc/self/task/{t}/comm").read().startswith("tf_XLAEigen")
               for t in os.listdir("/proc/self/task"))


def _identifier() -> Callable[[float], np.ndarray]:
    from eol_cal.firmware.kinematics import draw_sensor_errors, fingerprint_of
    from eol_cal.firmware.mech_params import FP_FORWARD, FP_REVERSE, unused_mech
    from eol_cal.firmware.mech_sim import PowerUp, simulate_powerups

    # as bench/bench_mech_id.py draws its 100-200 rpm band: the plant's encoders, true fingerprints
    N, P = 64, 6
    rng = np.random.default_rng(22)
    pus = []
    for i in range(500):
        err = draw_sensor_errors(np.random.default_rng(50_000 + i), N)
        fp, gp = fingerprint_of(err, P)
        mech = unused_mech(N).replace(fp_dirs=FP_FORWARD | FP_REVERSE, grid_phase=gp, fingerprint=fp)
        pus.append(PowerUp(err, mech, float(rng.uniform(0, 2 * math.pi)),
                           float(rng.choice([-1.0, 1.0]) * rng.uniform(100.0, 200.0)),
                           jitter_deg=0.002 if i % 2 else 0.0))

    def run(seconds: float) -> np.ndarray:
        res = simulate_powerups(pus, seconds, seed=10)
        return np.concatenate([res.first_id_s, res.wrong_ticks, res.r_first, res.score])

    return run


def _plant() -> Callable[[float], np.ndarray]:
    from eol_cal.firmware.contract import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, FLAGS_ESTIMATOR
    from eol_cal.plant.ecu_model import true_block
    from eol_cal.plant.presets import paper
    from eol_cal.plant.profile import constant
    from eol_cal.plant.simulate import simulate

    spec = paper()
    # layout 2, every estimator option: the identifying ECU (MECH_COMP_ENABLE where they allow it)
    block = true_block(spec, flags=FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR, mech=True)

    def run(seconds: float) -> np.ndarray:
        (res,) = simulate(spec, constant(120.0, seconds, iq=20.0), "compensated", blocks=block, seed=1)
        return np.concatenate([np.asarray(v, float).ravel() for _, v in sorted(vars(res).items())
                               if isinstance(v, np.ndarray)])

    return run


WORK = {"identifier": _identifier, "plant": _plant}
#: seconds simulated by the timed call
SECONDS = {"identifier": 2.0, "plant": 30.0}


def child(work: str) -> None:
    from eol_cal.numerics.xla import configure_xla, start_xla

    configure_xla()
    start_xla()
    run = WORK[work]()
    run(0.4)  # compile and warm
    c0, w0 = time.process_time(), time.perf_counter()
    out = run(SECONDS[work])
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    path = Path(os.environ["BENCH_OUT"])
    np.save(path, out)
    print(json.dumps({"wall": wall, "cpu": cpu, "pool": _pool_threads()}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--work", default="identifier,plant")
    ap.add_argument("--child")
    args = ap.parse_args()
    if args.child:
        child(args.child)
        return
    import tempfile

    print(f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f} at the start")
    with tempfile.TemporaryDirectory() as tmp:
        for work in args.work.split(","):
            rows: dict[str, list[dict]] = {name: [] for name in ALTERNATIVES}
            for r in range(args.rounds):
                for name, value in ALTERNATIVES.items():
                    out = Path(tmp) / f"{work}-{value}-{r}.npy"
                    env = {**os.environ, "EOL_CAL_XLA_THREADS": value, "BENCH_OUT": str(out)}
                    proc = subprocess.run([sys.executable, str(HERE), "--child", work], env=env,
                                          capture_output=True, text=True, check=True)
                    rows[name].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(f"\n{work}: {SECONDS[work]:g} s simulated, {args.rounds} rounds alternated (min / max)")
            print(f"  {'':32s} {'wall s':>13s} {'CPU s':>13s} {'cores':>11s} pool")
            for name, rs in rows.items():
                w = [x["wall"] for x in rs]
                c = [x["cpu"] for x in rs]
                k = [x["cpu"] / x["wall"] for x in rs]
                print(f"  {name:32s} {min(w):6.2f}/{max(w):6.2f} {min(c):6.2f}/{max(c):6.2f} "
                      f"{min(k):5.2f}/{max(k):5.2f} {rs[0]['pool']}")
            arrays = [np.load(p) for p in sorted(Path(tmp).glob(f"{work}-*.npy"))]
            diff = max(float(np.nanmax(np.abs(a - arrays[0]))) if a.shape == arrays[0].shape else float("inf")
                       for a in arrays)
            print(f"  results: {'equal' if diff == 0 else f'largest difference {diff:.3g}'}")
    print(f"load {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
