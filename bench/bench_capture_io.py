"""Capture I/O: read and write times and file sizes, side by side with what a user would write.

    python bench/bench_capture_io.py [--seconds 10] [--repeat 3]

A capture of the analytic model (20 kHz, torque, A/B, hall, iq_ref, speed) is written and read
as CSV and as MDF4 (digital channels as levels, and as change events). The alternatives are
the stdlib ``csv`` module (what one writes by hand) and ``numpy.genfromtxt`` reading the same
CSV, each reading the numbers only: no units, no metadata, no validation.
"""

from __future__ import annotations

import argparse
import csv
import functools
import tempfile
import time
from pathlib import Path

import numpy as np

from eol_cal.capture import read_capture, write_capture
from eol_cal.capture.synthetic import synthetic_capture


def best_of(repeat: int, func) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return min(times)


def stdlib_csv(path: Path) -> np.ndarray:
    with open(path, newline="") as fh:
        rows = [row for row in csv.reader(line for line in fh if not line.startswith("#"))]
    return np.array(rows[1:], dtype=np.float64)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    capture = synthetic_capture(seconds=args.seconds, fs=20000.0)
    n = len(capture.t)
    print(f"capture: {n} samples ({args.seconds:g} s at 20 kHz), {len(capture.channels) + 1} channels; best of {args.repeat}")
    print(f"{'what':44s} {'write s':>8s} {'read s':>8s} {'MB':>7s}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write_capture(capture, tmp / "warm.mf4")  # imports and first-call costs before timing
        read_capture(tmp / "warm.mf4")
        cases = [
            ("eol_cal CSV (units, metadata, validation)", "c.csv", {}),
            ("eol_cal MDF4 levels", "l.mf4", {"digital": "levels"}),
            ("eol_cal MDF4 events", "e.mf4", {"digital": "events"}),
        ]
        for label, name, opts in cases:
            path = tmp / name
            w = best_of(args.repeat, functools.partial(write_capture, capture, path, **opts))
            r = best_of(args.repeat, functools.partial(read_capture, path))
            print(f"{label:44s} {w:8.3f} {r:8.3f} {path.stat().st_size / 1e6:7.2f}")
        path = tmp / "c.csv"
        r = best_of(args.repeat, lambda: stdlib_csv(path))
        print(f"{'stdlib csv module, numbers only':44s} {'':>8s} {r:8.3f} {path.stat().st_size / 1e6:7.2f}")
        r = best_of(args.repeat, lambda: np.genfromtxt(path, delimiter=",", skip_header=16))
        print(f"{'numpy.genfromtxt, numbers only':44s} {'':>8s} {r:8.3f} {path.stat().st_size / 1e6:7.2f}")


if __name__ == "__main__":
    main()
