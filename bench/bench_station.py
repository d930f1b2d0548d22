"""Wall time of a full ``eol-cal run`` for one motor on the simulators, per step, against the
separate commands a user would otherwise chain in a shell script.

The simulators run in this process on 127.0.0.1 (as the dyno and the ECU are other machines on a
line): the dyno simulator (pymodbus, the built-in plant, a demo motor with ripple) and the ECU
simulator (python-can-remote). Each repeat gets a fresh ECU (flash erased) so the first
acquisition sees an uncompensated motor. The time the plant spends computing the captures is
measured inside the dyno simulator: on a real line that time is the shaft turning, on the
simulators it is CPU.

- ours: ``eol-cal run ... --json`` in its own process (process start, imports and the JAX
  persistent cache included); the per-step times come from its record. Both verification
  modes: ``--verify point`` (default: the compensated acquisition runs only the operating
  point's segments) and ``--verify full`` (the whole profile again).
- alternative: ``eol-cal block uncompensated``, ``flash`` (the run's prepare step), ``acquire``,
  ``fit``, ``table``, ``flash``, ``acquire``, ``analyze``, one process each, stopping at the first
  failing command.

    python bench/bench_station.py [--profile eol-default] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIMITS = ROOT / "fixtures" / "limits.toml"


def eol_cal(*args: str) -> list[str]:
    return [sys.executable, "-m", "cli.main", *args]


def timed(inner, spent: list[float]):
    """The dyno simulator's capture source ``inner`` (the rig's plant), timing each capture."""

    def source(req):
        t0 = time.perf_counter()
        try:
            return inner(req)
        finally:
            spent.append(time.perf_counter() - t0)

    return source


def run_ours(work: Path, profile: str, serial: str, seed: int, key: Path, env: dict, verify: str = "point") -> dict:
    from eol_cal.station.demo import loopback_station

    spent: list[float] = []
    with loopback_station(serial, seed, work / "sim") as st:
        st.dyno.sim.source = timed(st.dyno.sim.source, spent)
        t0 = time.perf_counter()
        t_spawn = time.time()
        p = subprocess.run(eol_cal("run", "--dyno", st.dyno_address, "--interface", "remote", "--channel", st.can_channel,
                                   "--limits", str(LIMITS), "--db", str(work / "results.sqlite"), "--serial", serial,
                                   "--profile", profile, "--key-file", str(key), "--report-dir", str(work / "reports"),
                                   "--spool-dir", str(work / "spool"), "--verify", verify, "--json"),
                           capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
        wall = time.perf_counter() - t0
        t_exit = time.time()
    if p.returncode not in (0, 1):
        raise RuntimeError(f"eol-cal run failed ({p.returncode}): {p.stderr[-2000:]}")
    rec = json.loads(p.stdout)["record"]
    steps = {s["step"]: s["seconds"] for s in rec["steps"]}
    from datetime import datetime

    started = datetime.fromisoformat(rec["started_at"]).timestamp()
    ended = datetime.fromisoformat(rec["ended_at"]).timestamp()
    return {"wall": wall, "steps": steps, "plant": sum(spent), "verdict": rec["verdict"],
            "captures": len(spent), "steps_sum": sum(steps.values()),
            "startup": started - t_spawn, "teardown": t_exit - ended}


def run_alternative(work: Path, profile: str, serial: str, seed: int, key: Path, env: dict) -> list[tuple[str, float, int]]:
    from eol_cal.station.demo import loopback_station

    out: list[tuple[str, float, int]] = []
    spent: list[float] = []
    with loopback_station(serial, seed, work / "sim-alt") as st:
        st.dyno.sim.source = timed(st.dyno.sim.source, spent)
        chain = [
            # the same measurement condition as eol-cal run's prepare step
            ("block uncompensated", eol_cal("block", "uncompensated", "--serial", serial, "-o", str(work / "prep.bin"))),
            ("flash uncompensated", eol_cal("flash", str(work / "prep.bin"), "--interface", "remote",
                                            "--channel", st.can_channel, "--key-file", str(key))),
            # with the ECU's bus: the capture records the block the ECU ran (fit refuses it otherwise)
            ("acquire", eol_cal("acquire", "--dyno", st.dyno_address, "--profile", profile, "--serial", serial,
                                "-o", str(work / "before.mf4"), "--interface", "remote", "--channel", st.can_channel)),
            ("fit", eol_cal("fit", str(work / "before.mf4"), "-o", str(work / "fit.json"))),
            ("table", eol_cal("table", str(work / "fit.json"), "-o", str(work / "block.bin"))),
            ("flash", eol_cal("flash", str(work / "block.bin"), "--interface", "remote", "--channel", st.can_channel,
                              "--key-file", str(key))),
            ("acquire compensated", eol_cal("acquire", "--dyno", st.dyno_address, "--profile", profile, "--serial", serial,
                                            "-o", str(work / "after.mf4"), "--interface", "remote",
                                            "--channel", st.can_channel)),
            ("analyze", eol_cal("analyze", str(work / "before.mf4"), str(work / "after.mf4"), "--json")),
        ]
        for name, cmd in chain:
            t0 = time.perf_counter()
            p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
            out.append((name, time.perf_counter() - t0, p.returncode))
            if p.returncode != 0:
                out.append((f"  ({name} exit {p.returncode}: {p.stderr.strip().splitlines()[-1][:100] if p.stderr.strip() else ''})", 0.0, p.returncode))
                break
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="eol-default")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    import logging

    from eol_cal.ecu import protocol as P

    for name in ("pymodbus", "isotp", "UdsClient", "Connection", "can", "can_remote"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    from cli.fit import enable_jax_cache

    enable_jax_cache()  # the simulators' plant in this process
    env = dict(os.environ)
    print(f"# {platform.node()} {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"profile {args.profile}, {args.repeat} repeats after one warm-up (JAX cache warm)")
    with tempfile.TemporaryDirectory(prefix="bench-station-") as tmp:
        tmp = Path(tmp)
        key = tmp / "key.hex"
        key.write_text(P.DEV_SECRET.hex())
        results: dict[str, list[dict]] = {"point": [], "full": []}
        for i in range(args.repeat + 1):
            for verify in ("point", "full"):
                work = tmp / f"run{i}-{verify}"
                work.mkdir()
                r = run_ours(work, args.profile, f"B-{i:04d}", 1, key, env, verify)
                if i:
                    results[verify].append(r)
                print(f"{'warm-up' if i == 0 else f'run {i}'} --verify {verify}: {r['wall']:.2f} s wall, verdict "
                      f"{r['verdict']}, plant {r['plant']:.2f} s over {r['captures']} captures", flush=True)
        for verify, runs in results.items():
            names = list(runs[0]["steps"])
            print(f"\n## eol-cal run --verify {verify}, median over the repeats (s)")
            print(f"{'step':<26}{'median':>9}{'min':>9}{'max':>9}")
            for n in names:
                v = [r["steps"].get(n, float('nan')) for r in runs]
                print(f"{n:<26}{statistics.median(v):9.2f}{min(v):9.2f}{max(v):9.2f}")
            for label, key_ in (("sum of steps", "steps_sum"), ("process start to cycle", "startup"),
                                ("cycle end to exit", "teardown"), ("process wall", "wall"),
                                ("plant compute (dyno sim)", "plant")):
                v = [r[key_] for r in runs]
                print(f"{label:<26}{statistics.median(v):9.2f}{min(v):9.2f}{max(v):9.2f}")
            tool = [r["wall"] - r["plant"] for r in runs]
            print(f"{'wall minus plant':<26}{statistics.median(tool):9.2f}{min(tool):9.2f}{max(tool):9.2f}")

        print("\n## alternative: separate eol-cal commands, one process each (s)")
        work = tmp / "alt"
        work.mkdir()
        total = 0.0
        for name, sec, rc in run_alternative(work, args.profile, "B-ALT", 1, key, env):
            total += sec
            print(f"{name:<22}{sec:9.2f}  exit {rc}" if sec else name)
        print(f"{'total':<22}{total:9.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
