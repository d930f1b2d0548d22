"""The identifier's power-ups simulated in JAX (``eol_cal.firmware.mech_sim.simulate_powerups``):
CPU per power-up and tick, this checkout against older ones, the results compared.

The scan is what ``tests/test_mech_identify.py`` runs for its 10 000 power-ups (20 parts of 500,
one speed band each from 30 to 300 rpm): the suite's largest single cost. Each checkout runs in a
fresh process of its own (its ``eol_cal`` and the test's parts imported from it), on XLA's one
thread; the rounds alternate the checkouts, so a change in the machine's load falls on all of
them. The first call of a process compiles the scan and is not counted.

    python bench/bench_powerups.py [--parts 0,5,10,19] [--seconds 1.0 | --whole] [--rounds 2] [--baseline DIR]

``--whole``: each part for the time the test runs it (six revolutions at its band's slowest
speed), so the identifier's evaluations (from the third revolution on) are in the figure; a
second of simulated time has none below ~180 rpm.

``--baseline DIR``: another checkout (``git worktree add DIR COMMIT``). Every part's
identification (first identification, offset, wrong ticks, resets of every power-up) is compared
by a SHA-256 of it; the last evaluation's score and margin by their largest difference in units
in the last place (binary32), since 2026-12-01 afternoon's scan sums an evaluation over fewer rows
than before (XLA may add them in another order). Since 2026-12-01 morning the encoder's jitter is
drawn by numpy, not by JAX's threefry in the scan: against older checkouts the results of a part
differ wherever a drawn jitter moves an edge by a tick, and the table then says how many power-ups
each checkout identified by then. In every checkout no power-up may identify a wrong offset or run
a tick with one (checked).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def child(parts: list[int], seconds: float | None, out: Path) -> None:
    """In the checkout's process: each part's CPU s per power-up and tick, and its results' hash."""
    from eol_cal.numerics.xla import start_xla

    start_xla()
    import numpy as np
    import test_mech_identify as T  # type: ignore[import-not-found]  # the test's parts, of this checkout

    from eol_cal.firmware.mech_sim import TICK_HZ, simulate_powerups

    pus, _, _ = T._part(parts[0])
    simulate_powerups(pus, 0.05, seed=0)  # the scan compiled for the batch's shape
    rows = []
    for part in parts:
        pus, whole, _ = T._part(part)
        run_s = whole if seconds is None else seconds
        t0 = time.process_time()
        res = simulate_powerups(pus, run_s, seed=part)
        cpu = time.process_time() - t0
        digest = hashlib.sha256()
        for name in ("truth", "first_id_s", "r_first", "wrong_ticks", "active_end", "resets"):
            digest.update(np.ascontiguousarray(getattr(res, name)).tobytes())
        hit = np.isfinite(res.first_id_s)
        rows.append({"part": part, "powerups": len(pus), "cpu_s": cpu, "seconds": run_s,
                     "ns_per_tick": 1e9 * cpu / (len(pus) * run_s * TICK_HZ), "sha256": digest.hexdigest()[:16],
                     "score": np.asarray(res.score, np.float32).tolist(), "margin": np.asarray(res.margin, np.float32).tolist(),
                     "identified": int(hit.sum()),
                     "wrong": int(res.wrong_ticks.sum() + (res.r_first[hit] != res.truth[hit]).sum())})
    out.write_text(json.dumps(rows))


def _max_ulp(a: list[float], b: list[float]) -> int:
    """Largest distance between two lists of binary32 numbers, in units in the last place (NaN = NaN)."""
    import numpy as np

    x, y = np.asarray(a, np.float32), np.asarray(b, np.float32)
    both = np.isnan(x) & np.isnan(y)
    if (np.isnan(x) != np.isnan(y)).any():
        return 1 << 31
    ix, iy = (v.view(np.int32).astype(np.int64) for v in (x, y))
    ix, iy = (np.where(v < 0, -(1 << 31) - v, v) for v in (ix, iy))  # sign-magnitude to ordered integers
    return int(np.abs(ix - iy)[~both].max(initial=0))


def run(code: Path, parts: list[int], seconds: float | None) -> list[dict]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(code), str(code / "tests")]))  # the test's parts too
    with tempfile.NamedTemporaryFile(suffix=".json") as f:
        span = ["--whole"] if seconds is None else ["--seconds", str(seconds)]
        subprocess.run([sys.executable, str(HERE / "bench_powerups.py"), "--child", "--parts",
                        ",".join(map(str, parts)), "--out", f.name, *span],
                       check=True, env=env, cwd=code)
        return json.loads(Path(f.name).read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="0,5,10,19", help="the test's parts (speed bands 0..19), comma-separated")
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated seconds of each part's 500 power-ups")
    ap.add_argument("--whole", action="store_true", help="each part for the test's time (six revolutions at its slowest speed)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--baseline", action="append", default=[], type=Path, help="an older checkout (repeatable)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    parts = [int(p) for p in args.parts.split(",")]
    seconds = None if args.whole else args.seconds
    if args.child:
        child(parts, seconds, args.out)
        return
    codes = {"this checkout": HERE.parent, **{str(b): b.resolve() for b in args.baseline}}
    best: dict[str, dict[int, dict]] = {name: {} for name in codes}
    print(f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}; parts {parts}, "
          + ("each for the test's time" if seconds is None else f"{seconds:g} s simulated each"))
    for r in range(args.rounds):
        for name, code in codes.items():
            rows = run(code, parts, seconds)
            print(f"round {r + 1}: {name:40s} " + "  ".join(f"part {x['part']} {x['ns_per_tick']:.0f} ns" for x in rows)
                  + f"; load {os.getloadavg()[0]:.2f}", flush=True)
            for x in rows:
                kept = best[name].get(x["part"])
                best[name][x["part"]] = x if kept is None or x["cpu_s"] < kept["cpu_s"] else kept
    print("\nCPU ns per power-up and tick, best of the rounds (500 power-ups a part, XLA on one thread)")
    print(f"{'part (speed band)':20s}" + "".join(f"{name[-28:]:>30s}" for name in codes))
    for p in parts:
        print(f"{p:<20d}" + "".join(f"{best[name][p]['ns_per_tick']:30.0f}" for name in codes))
    if seconds is None:
        print("\nCPU s of each part for the test's time, best of the rounds")
        for p in parts:
            print(f"{p:<20d}" + "".join(f"{best[name][p]['cpu_s']:30.2f}" for name in codes))
        print(f"{'all of them':20s}" + "".join(f"{sum(best[name][p]['cpu_s'] for p in parts):30.2f}" for name in codes))
    same = all(len({best[name][p]["sha256"] for name in codes}) == 1 for p in parts)
    print(f"identification the same in every checkout: {'yes' if same else 'no (the jitter drawn otherwise)'}")
    first = next(iter(codes))
    ulp = max(_max_ulp(best[first][p][k], best[name][p][k]) for name in codes for p in parts for k in ("score", "margin"))
    print(f"last evaluation's score and margin: largest difference from {first!r} {ulp} units in the last place")
    if not same:
        print(f"power-ups identified by the end{'':3s}" + "".join(f"{name[-28:]:>30s}" for name in codes))
        for p in parts:
            print(f"{p:<20d}" + "".join(f"{best[name][p]['identified']:30d}" for name in codes))
    wrong = sum(best[name][p].get("wrong", 0) for name in codes for p in parts)
    print(f"power-ups with a wrong offset or a tick run with one: {wrong}")
    if wrong:
        sys.exit(1)


if __name__ == "__main__":
    main()
