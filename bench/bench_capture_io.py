"""Capture I/O: read and write times and file sizes, side by side with what a user would write.

    python bench/bench_capture_io.py [--seconds 10] [--repeat 3]

A capture of the analytic model (20 kHz, torque, A/B, hall, iq_ref, speed) is written and read
as CSV and as MDF4 (digital channels as levels, and as change events). The alternatives are
the stdlib ``csv`` module (what one writes by hand) and ``numpy.genfromtxt`` reading the same
CSV, each reading the numbers only: no units, no metadata, no validation.

A lab's DAQ files (issue 38): the same capture as a TDMS file (written by npTDMS as a DAQmx task
writes one: waveforms, torque in N*cm) and as a tab-separated decimal-comma export with a units
row, each read through a channel map; beside them what one would use instead, npTDMS's
``TdmsFile.read`` and ``pandas.read_csv(sep="\t", decimal=",")``, numbers only.
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


def write_daq_files(capture, tmp: Path) -> tuple[float, float]:
    """The capture as a DAQmx task's TDMS and as a German spreadsheet's TSV, each with its map;
    the seconds each took to write."""
    from nptdms import ChannelObject, GroupObject, RootObject, TdmsWriter

    names = {"torque": "Moment", "enc_a": "A", "enc_b": "B", "hall": "Hall", "iq_ref": "Iq", "speed": "n"}
    units = {"torque": "N*cm", "iq_ref": "A", "speed": "1/min"}
    scale = {"torque": 100.0}
    wf = {"wf_increment": float(capture.t[1] - capture.t[0])}
    start = time.perf_counter()
    with TdmsWriter(str(tmp / "c.tdms")) as writer:
        writer.write_segment([RootObject(properties=dict(capture.metadata)), GroupObject("AI"), *(
            ChannelObject("AI", names[k], np.asarray(capture[k]) * scale.get(k, 1),
                          properties={**wf, "unit_string": units.get(k, "")}) for k in names)])
    tdms_s = time.perf_counter() - start
    (tmp / "tdms.toml").write_text("[channels]\n" + "".join(f'{k} = {{ name = "AI/{v}" }}\n' for k, v in names.items()))
    start = time.perf_counter()
    columns = [capture.t, *(capture[k] for k in names)]
    with open(tmp / "c.txt", "w", encoding="utf-8") as fh:
        fh.writelines(f"# {k}: {v}\n" for k, v in capture.metadata.items())
        fh.write("Zeit\t" + "\t".join(names.values()) + "\ns\tN*m\t\t\t\tA\trpm\n")
        fh.writelines("\t".join(repr(v).replace(".", ",") for v in row) + "\n"
                      for row in zip(*(c.tolist() for c in columns), strict=True))
    txt_s = time.perf_counter() - start
    (tmp / "text.toml").write_text('[channels]\nt = { name = "Zeit" }\n' + "".join(
        f'{k} = {{ name = "{v}" }}\n' for k, v in names.items())
        + '[file]\nformat = "text"\ndelimiter = "\\t"\ndecimal = ","\nunits_row = true\n')
    return tdms_s, txt_s


def daq_rows(capture, tmp: Path, repeat: int) -> None:
    """The TDMS and text rows, each beside the library a user would read it with."""
    from nptdms import TdmsFile

    tdms_s, txt_s = write_daq_files(capture, tmp)
    meta_lines = len(capture.metadata)
    rows = [
        ("eol_cal TDMS via map (npTDMS underneath)", tdms_s, functools.partial(read_capture, tmp / "c.tdms", tmp / "tdms.toml"),
         "c.tdms"),
        ("npTDMS TdmsFile.read, numbers only", None, lambda: TdmsFile.read(tmp / "c.tdms"), "c.tdms"),
        ("eol_cal TSV, decimal comma, units row, via map", txt_s, functools.partial(read_capture, tmp / "c.txt",
                                                                                   tmp / "text.toml"), "c.txt"),
    ]
    try:
        import pandas as pd

        rows.append(("pandas.read_csv(sep=tab, decimal=','), numbers only", None,
                     lambda: pd.read_csv(tmp / "c.txt", sep="\t", decimal=",", skiprows=[*range(meta_lines), meta_lines + 1]),
                     "c.txt"))
    except ImportError:  # pandas is no dependency of eol-cal: the row is left out without it
        pass
    for label, w, func, name in rows:
        func()  # first-call costs (pint's unit registry for N*cm) before timing, as for the rows above
        r = best_of(repeat, func)
        written = f"{w:8.3f}" if w is not None else f"{'':>8s}"
        print(f"{label:52s} {written} {r:8.3f} {(tmp / name).stat().st_size / 1e6:7.2f}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    capture = synthetic_capture(seconds=args.seconds, fs=20000.0)
    n = len(capture.t)
    print(f"capture: {n} samples ({args.seconds:g} s at 20 kHz), {len(capture.channels) + 1} channels; best of {args.repeat}")
    print(f"{'what':52s} {'write s':>8s} {'read s':>8s} {'MB':>7s}")
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
            print(f"{label:52s} {w:8.3f} {r:8.3f} {path.stat().st_size / 1e6:7.2f}")
        path = tmp / "c.csv"
        r = best_of(args.repeat, lambda: stdlib_csv(path))
        print(f"{'stdlib csv module, numbers only':52s} {'':>8s} {r:8.3f} {path.stat().st_size / 1e6:7.2f}")
        r = best_of(args.repeat, lambda: np.genfromtxt(path, delimiter=",", skip_header=16))
        print(f"{'numpy.genfromtxt, numbers only':52s} {'':>8s} {r:8.3f} {path.stat().st_size / 1e6:7.2f}")
        daq_rows(capture, Path(tmp), args.repeat)


if __name__ == "__main__":
    main()
