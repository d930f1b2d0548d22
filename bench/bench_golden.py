"""``eol-cal golden --check`` from process start to verdict (issue 37 item 5: at most 15 s on an idle
2-core machine), this checkout against an older one, and on one core.

    python bench/bench_golden.py [--rounds 1] [--baseline DIR] [--one-core]

Each run is a fresh ``python -m cli.main golden --check`` of this tree's ``firmware_params/golden``
(every vector set recomputed); the rounds alternate the runs, so a change in the machine's load falls
on all of them. ``cpu`` is the CPU time (user + system) of the run and the processes it started,
which other jobs on the machine move much less than the wall time; ``load`` is the 1-minute load
average when the run ended.

- ``this``: the code of this checkout (the scenario files in one process a core);
- ``--one-core``: the same pinned to one core (``taskset -c 0``): the scenarios one after the other;
- ``--baseline DIR``: the code of another checkout (``git worktree add DIR COMMIT``, or an
  extracted ``git archive``), its ``eol_cal`` and ``cli`` imported instead of this one's.

Every run must say the files are identical (checked).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def run_check(code: Path, pin: bool) -> tuple[float, float]:
    """(wall s, CPU s) of one ``golden --check`` with the code of checkout ``code``."""
    env = dict(os.environ, PYTHONPATH=str(code))
    cmd = [sys.executable, "-m", "cli.main", "golden", "--check", str(ROOT / "firmware_params" / "golden")]
    if pin:
        taskset = shutil.which("taskset")
        if taskset is None:
            raise SystemExit("--one-core needs taskset (util-linux)")
        cmd = [taskset, "-c", "0", *cmd]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0 or "identical" not in res.stdout:
        raise SystemExit(f"{code}: golden --check failed ({res.returncode}):\n{res.stdout}{res.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--baseline", type=Path, default=None, help="a checkout of older code to run side by side")
    ap.add_argument("--one-core", action="store_true", help="also this code pinned to one core")
    a = ap.parse_args()
    runs = [("this", ROOT, False)]
    if a.one_core:
        runs.append(("this, one core", ROOT, True))
    if a.baseline is not None:
        runs.append(("baseline", a.baseline.resolve(), False))
    got: dict[str, list[tuple[float, float, float]]] = {name: [] for name, _, _ in runs}
    print(f"cores: {len(os.sched_getaffinity(0))}, load at start {os.getloadavg()[0]:.1f}", flush=True)
    for _ in range(a.rounds):
        for name, code, pin in runs:
            wall, cpu = run_check(code, pin)
            got[name].append((wall, cpu, os.getloadavg()[0]))
            print(f"  {name}: {wall:.1f} s wall, {cpu:.1f} s CPU, load {got[name][-1][2]:.1f}", flush=True)
    print(f"{'':<16}{'wall s':>9}{'cpu s':>9}{'load':>7}")
    for name, rows in got.items():
        wall, cpu, load = min(rows)
        print(f"{name:<16}{wall:>9.1f}{cpu:>9.1f}{load:>7.1f}")
    if a.baseline is not None:
        w0, c0, _ = min(got["baseline"])
        w1, c1, _ = min(got["this"])
        print(f"this: {w0 / w1:.2f}x the baseline's wall, {c0 / c1:.2f}x its CPU")


if __name__ == "__main__":
    main()
