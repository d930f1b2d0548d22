"""How long an ``eol-cal`` process lives after its last output: the process ends at its last
atexit handler (``cli.main.end_process``) against Python's own teardown after it, the alternative a
plain ``python -m`` entry point gets (module finalization, XLA's threads and destructors).

A line that drives ``eol-cal run`` from its own sequencer waits for the process to end before it
starts the next motor, and a signal in Python's teardown could not give exit 2 (its handlers are
reset there). Both variants run the same command, alternated, in one run: ``eol-cal fit`` of a
simulated eol-default capture (JAX traced and solved, as in ``eol-cal run``).

    python bench/bench_exit.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {
    "ends at the last atexit handler (main)": "from cli import main as m; m.main()",
    "Python's own teardown after it": "from cli import main as m; m.end_process = lambda: None; m.main()",
}


def _once(code: str, args: list[str]) -> tuple[float, float, int]:
    """(wall s, last output line to process end s, exit status) of one process."""
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-c", f"import sys; sys.argv[0] = 'eol-cal'; {code}", *args],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    last = t0
    for _line in proc.stdout:
        last = time.monotonic()
    proc.wait()
    end = time.monotonic()
    return end - t0, end - last, proc.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    opts = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        capture = Path(tmp) / "eol.mf4"
        subprocess.run([sys.executable, "-m", "cli.main", "simulate", "-o", str(capture), "--profile", "eol-default"],
                       cwd=ROOT, check=True, capture_output=True)
        args = ["fit", str(capture), "-o", str(Path(tmp) / "fit.json"), "--json"]
        times: dict[str, list[tuple[float, float, int]]] = {name: [] for name in VARIANTS}
        for _ in range(opts.repeat):
            for name, code in VARIANTS.items():
                times[name].append(_once(code, args))
    print(f"eol-cal fit of a simulated eol-default capture, {opts.repeat} processes each, alternated; median (min-max) s")
    print(f"{'variant':42s} {'wall':>18s} {'last output -> end':>22s}  exit")
    for name, rows in times.items():
        walls, tails, codes = zip(*rows, strict=True)
        print(f"{name:42s} {statistics.median(walls):6.2f} ({min(walls):.2f}-{max(walls):.2f})"
              f" {statistics.median(tails):10.2f} ({min(tails):.2f}-{max(tails):.2f})  {sorted(set(codes))}")


if __name__ == "__main__":
    main()
