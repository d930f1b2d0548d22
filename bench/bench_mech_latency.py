"""The latency the background evaluation adds to the identification (contract revision 1.2,
firmware_params/MECH.md "Background"), measured by the twin: revolutions from power-up to
identification at 30-300 rpm, forward and reverse, the same power-ups run by this checkout's
identifier and by another checkout's (the evaluation in the tick), side by side.

    python bench/bench_mech_latency.py --out new.json                      # this checkout
    PYTHONPATH=/path/to/old/checkout python bench/bench_mech_latency.py --out old.json
    python bench/bench_mech_latency.py --compare old.json new.json

Each power-up: a plant encoder drawn with production pitch errors (its true fingerprint in the
block), a random start angle, constant speed, no timing noise; ``eol_cal.firmware.mech_sim`` (the
estimator and identifier in JAX, one background slice per tick as the golden vectors run it).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

SPEEDS = (30.0, 60.0, 100.0, 200.0, 300.0)


def run(per_point: int) -> dict[str, list[float]]:

    from eol_cal.firmware.mech_params import FP_FORWARD, FP_REVERSE, unused_mech
    from eol_cal.firmware.mech_sim import PowerUp, simulate_powerups
    from eol_cal.firmware.kinematics import draw_sensor_errors, fingerprint_of

    N, P = 64, 6
    out: dict[str, list[float]] = {}
    for rpm in SPEEDS:
        for sign in (1.0, -1.0):
            rng = np.random.default_rng(int(rpm))
            pus = []
            for i in range(per_point):
                err = draw_sensor_errors(np.random.default_rng(70_000 + i), N)
                fp, gp = fingerprint_of(err, P)
                mech = unused_mech(N).replace(fp_dirs=FP_FORWARD | FP_REVERSE, grid_phase=gp, fingerprint=fp)
                pus.append(PowerUp(err, mech, float(rng.uniform(0, 2 * math.pi)), sign * rpm))
            t0 = time.perf_counter()
            res = simulate_powerups(pus, 6.0 * 60.0 / rpm, seed=int(rpm))
            revs = res.first_id_s * rpm / 60.0
            ok = np.isfinite(res.first_id_s) & (res.r_first == res.truth)
            key = f"{sign * rpm:+.0f}"
            out[key] = [float(v) if k else math.nan for v, k in zip(revs, ok, strict=True)]
            print(f"{key:>6} rpm: identified {int(ok.sum())}/{per_point}, revolutions median "
                  f"{np.nanmedian(revs):.3f}, wall {time.perf_counter() - t0:.1f} s", flush=True)
    return out


def compare(old: dict[str, list[float]], new: dict[str, list[float]]) -> None:
    print(f"{'rpm':>6} {'old median':>11} {'new median':>11} {'added median':>13} {'added max':>10} "
          f"{'added ticks median':>19}")
    for key in old:
        a, b = np.asarray(old[key]), np.asarray(new[key])
        d = b - a
        ticks = d * 60.0 / abs(float(key)) * 20000.0
        print(f"{key:>6} {np.nanmedian(a):>11.3f} {np.nanmedian(b):>11.3f} {np.nanmedian(d):>13.4f} "
              f"{np.nanmax(d):>10.4f} {np.nanmedian(ticks):>19.0f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-point", type=int, default=16, help="power-ups per speed and direction")
    ap.add_argument("--out", help="write the revolutions to identification (JSON)")
    ap.add_argument("--compare", nargs=2, metavar=("OLD", "NEW"), help="compare two runs")
    args = ap.parse_args()
    if args.compare:
        old, new = (json.loads(Path(p).read_text()) for p in args.compare)
        compare(old, new)
        return
    res = run(args.per_point)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f)


if __name__ == "__main__":
    main()
