"""A type-1 gauge study of the simulated station: one master motor run 1 + N times (default 25)
through the whole station cycle (``eol-cal run``: pre-flight, prepare, acquire, fit, table,
flash, acquire compensated, metrics, record), then ``eol-cal msa type1`` over its runs.

The master is one motor drawn from the plant's production spread (``plant.variation`` seed
``--seed``) and stays on the dyno for all runs, with its own ECU simulator (each run flashes
it again); the dyno simulator's plant draws new transducer and current-sensor noise for every
capture (seed x 1000 + capture index), so the plant's noise is the only spread: what a type-1
study measures. The reference of k6 is the plant's true k6 (the simulator knows it), so the
bias is the fit's own; the other quantities' references are the first run's values (the
declared reference run, ``--reference-run``; not one of the N). The tolerances of k6 and the
p-p figures are the demo variant's upper limits - 0; phase_k6 and c6 get none (no limit):
their bias and repeatability are shown without Cg/Cgk.

As a check the script recomputes s, bias, Cg and Cgk of k6 from the records' JSON with numpy
and scipy (``ttest_1samp``), independently of :mod:`eol_cal.msa`.

    python bench/bench_msa_type1.py [--runs 25] [--seed 7] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SERIAL = "MASTER-0001"


def eol_cal(*args: str) -> list[str]:
    return [sys.executable, "-m", "cli.main", *args]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=25, help="the study's runs (one more is run first: the reference)")
    ap.add_argument("--seed", type=int, default=7, help="the master motor's draw from the production spread")
    ap.add_argument("--out", type=Path, default=None, help="keep the database, reports, page and plots here")
    args = ap.parse_args()

    import logging

    import numpy as np
    from scipy import stats

    from cli.fit import enable_jax_cache
    from cli.station import DEMO_LIMITS
    from eol_cal.ecu import protocol as P
    from eol_cal.sim.loopback import demo_motor_spec, loopback_station
    from eol_cal.records.record import RunRecord

    for name in ("pymodbus", "isotp", "UdsClient", "Connection", "can", "can_remote"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    from eol_cal.numerics.xla import configure_xla

    configure_xla()  # the simulators' plant in this process, as `eol-cal dyno-sim` and the demo run it
    enable_jax_cache()
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    print(f"# {platform.node()} {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"load average {' '.join(load)}; {args.runs} runs of {SERIAL} (motor seed {args.seed})")
    tmp = None
    if args.out is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench-msa-")
        out = Path(tmp.name)
    else:
        out = args.out
        out.mkdir(parents=True, exist_ok=True)
    key = out / "key.hex"
    key.write_text(P.DEV_SECRET.hex())
    limits = out / "limits.toml"
    limits.write_text(DEMO_LIMITS)
    db = out / "master.sqlite"
    spec = demo_motor_spec(args.seed, SERIAL)
    k6_true = spec.k6 * 1e3  # mN*m/A
    # the station names the master (docs/station.md, "Master motor"): its runs are kind master, checked
    # against the true k6 +- 0.1 mN*m/A
    env = {**os.environ, "EOL_CAL_MASTER_SERIAL": SERIAL, "EOL_CAL_MASTER_EVERY_H": "8",
           "EOL_CAL_MASTER_REFERENCE_K6": f"{k6_true:.6f}", "EOL_CAL_MASTER_TOLERANCE_K6": "0.1"}
    t0 = time.perf_counter()
    k6, ids = [], []
    with loopback_station(SERIAL, args.seed, out / "sim", spec_for=lambda req: spec) as st:
        for i in range(args.runs + 1):
            p = subprocess.run(eol_cal("run", "--dyno", st.dyno_address, "--interface", "remote", "--channel", st.can_channel,
                                       "--limits", str(limits), "--db", str(db), "--serial", SERIAL,
                                       "--key-file", str(key), "--report-dir", str(out / "reports"),
                                       "--spool-dir", str(out / "spool"), "--json"),
                               capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
            if p.returncode not in (0, 1):
                raise RuntimeError(f"eol-cal run failed ({p.returncode}): {p.stderr[-2000:]}")
            rec = RunRecord.from_json(json.loads(p.stdout)["record"], "eol-cal run --json")
            value = rec.value("k6") * 1e3
            ids.append(rec.run_id)
            if i:
                k6.append(value)
            print(f"run {i:2d}{' (reference)' if i == 0 else ''}: {rec.kind} {rec.verdict:5s} k6 {value:.5f} mN*m/A  "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
    wall = time.perf_counter() - t0
    cmd = ["msa", "type1", "--db", str(db), "--serial", SERIAL, "--reference-run", ids[0], "--reference",
           f"k6={k6_true!r}", "--json", "-o", str(out / "type1.html"), "--plots", str(out / "plots")]
    p = subprocess.run(eol_cal(*cmd), capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    if p.returncode not in (0, 1):
        raise RuntimeError(f"eol-cal msa type1 failed ({p.returncode}): {p.stderr[-2000:]}")
    doc = json.loads(p.stdout)
    print(f"\n{args.runs + 1} station cycles in {wall:.0f} s; eol-cal {' '.join(cmd[:5])} ... (exit {p.returncode})")
    print("| quantity | unit | n | x_ref | mean | s | bias | p (bias) | T | Cg | Cgk |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for q in doc["quantities"]:
        def f(x, d=4):
            return "-" if x is None else f"{x:.{d}g}"
        print(f"| {q['key']} | {q['unit']} | {q['n']} | {f(q['reference'])} | {f(q['mean'], 5)} | {f(q['sd'], 3)} | "
              f"{f(q['bias'], 3)} | {f(q['p_value'], 2)} | {f(q['tolerance'])} | "
              f"{f(q['cg'], 3) if q['cg'] is not None else q['cg_reason']} | "
              f"{f(q['cgk'], 3) if q['cgk'] is not None else q['cgk_reason']} |")
    # the check: numpy / scipy from the records' k6, not through eol_cal.msa
    x = np.array([v for v in k6 if np.isfinite(v)])
    tol = next(q["tolerance"] for q in doc["quantities"] if q["key"] == "k6")
    s = x.std(ddof=1)
    bias = x.mean() - k6_true
    print(f"\ncheck (numpy/scipy on the records' k6): n {len(x)}, s {s:.4g}, Cg {0.2 * tol / (4 * s):.4g}, "
          f"bias {bias:.4g}, Cgk {(0.1 * tol - abs(bias)) / (2 * s):.4g}, p {stats.ttest_1samp(x, k6_true).pvalue:.2g}")
    print(f"capable: {doc['capable']}; page {out / 'type1.html'}")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
