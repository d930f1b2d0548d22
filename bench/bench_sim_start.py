"""A simulated station's start, what every ``eol-cal station --demo``, ``eol-cal run --demo`` and
dyno simulator pays before its first motor, against an older checkout:

- ``prepare``: the built-in plant's programs made ready for the cycle's two blocks
  (:func:`eol_cal.sim.rig.prepare_plant`, the first call in the process, the paper motor and the
  estimator options of the demo's limits): traced, or read back as ``jax.export`` files;
- ``ecu child``: the loopback ECU's child process from its start to its first answer (its URL)
  and its end (:func:`eol_cal.sim.remote_ecu.spawn_remote`): the child's CPU.

Each checkout runs in fresh processes of its own with a cache directory of its own (JAX's
compilation cache and the exported programs; a first run per checkout fills it and is not
counted), alternated ``--rounds`` times; CPU s is user + system of the process and its children.

    python bench/bench_sim_start.py [--rounds 3] [--baseline DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve()


def _cpu(who: int) -> float:
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def child(what: str) -> dict[str, float]:
    """One measurement in this (fresh) process."""
    from eol_cal.analysis.fit.cache import default_cache_dir, enable_compile_cache

    enable_compile_cache(default_cache_dir())
    if what == "prepare":
        from eol_cal.records.limits import load_limits
        from eol_cal.sim.loopback import demo_motor_spec
        from eol_cal.sim.rig import prepare_plant

        options = load_limits(str(HERE.parents[1] / "eol_cal" / "station" / "demo-limits.toml")).estimator_options
        spec = demo_motor_spec(1, "M-0001")
        c, t = _cpu(resource.RUSAGE_SELF), time.perf_counter()
        prepare_plant(lambda req: spec, options, "M-0001", 1)
        return {"cpu": _cpu(resource.RUSAGE_SELF) - c, "wall": time.perf_counter() - t}
    from eol_cal.sim.remote_ecu import spawn_remote

    with tempfile.TemporaryDirectory() as d:
        c, t = _cpu(resource.RUSAGE_CHILDREN), time.perf_counter()
        ecu = spawn_remote(Path(d) / "ecu.flash", host="127.0.0.1", port=0)
        assert ecu.url.startswith("ws://")
        ecu.close()
        return {"cpu": _cpu(resource.RUSAGE_CHILDREN) - c, "wall": time.perf_counter() - t}


def _run(code: Path, cache: Path, what: str) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(code), EOL_CAL_JAX_CACHE=str(cache))
    out = subprocess.run([sys.executable, str(HERE), "--child", what], env=env, cwd=code, capture_output=True,
                         text=True, timeout=900, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--baseline", type=Path, help="another checkout (git worktree) to compare with")
    ap.add_argument("--child", choices=("prepare", "ecu"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(child(a.child)))
        return
    codes = {"this": HERE.parents[1]}
    if a.baseline is not None:
        codes["baseline"] = a.baseline.resolve()
    print(f"cores {os.cpu_count()}, load {os.getloadavg()[0]:.2f} at the start", flush=True)
    got: dict[tuple[str, str], list[dict[str, float]]] = {}
    with tempfile.TemporaryDirectory() as d:
        caches = {name: Path(d) / name for name in codes}
        for name, code in codes.items():  # the first run of each fills its caches: not counted
            _run(code, caches[name], "prepare")
        for r in range(a.rounds):
            for what in ("prepare", "ecu"):
                for name, code in codes.items():
                    m = _run(code, caches[name], what)
                    got.setdefault((what, name), []).append(m)
                    print(f"round {r + 1}: {what:8s} {name:9s} CPU {m['cpu']:.2f} s, wall {m['wall']:.2f} s", flush=True)
    print(f"\nmedian of {a.rounds} fresh processes (min-max), load {os.getloadavg()[0]:.2f} at the end")
    print(f"{'what':10s} {'checkout':10s} {'CPU s':>18s} {'wall s':>18s}")
    for (what, name), ms in got.items():
        cpu, wall = [m["cpu"] for m in ms], [m["wall"] for m in ms]
        print(f"{what:10s} {name:10s} {statistics.median(cpu):6.2f} ({min(cpu):.2f}-{max(cpu):.2f}) "
              f"{statistics.median(wall):6.2f} ({min(wall):.2f}-{max(wall):.2f})")


if __name__ == "__main__":
    main()
