"""The CAN commands as processes: ``eol-cal ecu-sim`` until it serves, and ``eol-cal flash``
from its start to its exit, wall and CPU seconds, this checkout against older ones.

What a tester at the station waits for, and what every such process of the test suite costs:
python-can's own import brings asammdf and pandas for its MF4 logger unless eol-cal masks it
(:mod:`eol_cal.python_can`). Each checkout's commands run from its own directory, the rounds
alternate the checkouts, and every flash must end with exit 0 and the new block active.

    python bench/bench_cli_can.py [--rounds 5] [--baseline DIR ...]

``--baseline DIR``: another checkout (``git worktree add DIR COMMIT``).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import flash_block, hmac_seed_to_key
from eol_cal.ecu.flash import NorFlash, select_active
from eol_cal.sim.virtual_rig import FAST_CLIENT, example_block, virtual_rig

HERE = Path(__file__).resolve().parent


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def one(code: Path, work: Path) -> dict[str, float]:
    """One ecu-sim serving a fresh copy of the old flash image, one flash of the new block into it."""
    image = work / "ecu.bin"
    image.write_bytes((work / "base.bin").read_bytes())
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the checkout's own eol_cal (its cwd)
    cli = [sys.executable, "-m", "cli.main"]
    c0, t0 = _children_cpu(), time.monotonic()
    sim = subprocess.Popen([*cli, "ecu-sim", "--flash-file", str(image), "--listen", "127.0.0.1:0"], cwd=code, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = sim.stdout.readline().strip()  # type: ignore[union-attr]
        served = time.monotonic() - t0
        if not url.startswith("ws://"):
            raise SystemExit(f"{code}: ecu-sim did not start: {sim.stderr.read()}")  # type: ignore[union-attr]
        c1, t1 = _children_cpu(), time.monotonic()
        res = subprocess.run([*cli, "flash", str(work / "new.bin"), "-i", "remote", "-c", url,
                              "--key-file", str(work / "key.hex")], cwd=code, env=env, capture_output=True, text=True)
        flash_wall, flash_cpu = time.monotonic() - t1, _children_cpu() - c1
        if res.returncode != 0:
            raise SystemExit(f"{code}: flash exit {res.returncode}: {res.stderr}")
    finally:
        sim.terminate()
        sim.wait(10)
    if select_active(NorFlash(image))[0].sequence != 2:
        raise SystemExit(f"{code}: the new block is not the active one")
    return {"ecu-sim serving s": served, "flash wall s": flash_wall, "flash CPU s": flash_cpu,
            "both CPU s": _children_cpu() - c0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--baseline", action="append", default=[], type=Path, help="an older checkout (repeatable)")
    args = ap.parse_args()
    codes = {"this checkout": HERE.parent, **{str(b): b.resolve() for b in args.baseline}}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        with virtual_rig(work / "base.bin") as rig:  # bank 0 holds the old block, sequence 1
            flash_block(rig.tester, example_block(seed=1), seed_to_key=hmac_seed_to_key(P.DEV_SECRET), timing=FAST_CLIENT)
        (work / "key.hex").write_text(P.DEV_SECRET.hex())
        (work / "new.bin").write_bytes(example_block(seed=2))
        rows: dict[str, list[dict[str, float]]] = {name: [] for name in codes}
        print(f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}; {args.rounds} rounds, the checkouts alternated")
        for r in range(args.rounds):
            for name, code in codes.items():
                rows[name].append(one(code, work))
                x = rows[name][-1]
                print(f"round {r + 1}: {name[-40:]:40s} " + ", ".join(f"{k} {v:.2f}" for k, v in x.items())
                      + f"; load {os.getloadavg()[0]:.2f}", flush=True)
    keys = list(next(iter(rows.values()))[0])
    print("\nmedian over the rounds")
    print(f"{'':22s}" + "".join(f"{name[-28:]:>30s}" for name in codes))
    for k in keys:
        print(f"{k:22s}" + "".join(f"{statistics.median(x[k] for x in rows[name]):30.2f}" for name in codes))


if __name__ == "__main__":
    main()
