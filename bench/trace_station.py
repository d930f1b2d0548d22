"""Where a station cycle's time goes: one motor's timeline of every UDS and Modbus exchange.

Runs `eol-cal station --log-file` against the benchmark's real-time line (bench_station.py's
simulators, in this process), a warm-up motor and then ``--motors`` counted ones, and prints for
the last motor its steps (start and length, from the record) and the exchange log folded: runs of
status polls and of buffer reads in one line each, every other exchange as it came, with its time
from the scan (s). What bench_station.py measures per step, this shows inside the steps: a read
of the buffer after a capture instead of during it, a wait between two requests, a step's bus
frames.

    python bench/trace_station.py [--motors 1] [--setup default@500000] [--out DIR]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bench_station as bs  # the benchmark's line and helpers (beside this script: on the path of a script run)

LINE = re.compile(r"(\S+)Z (\S+) (\S+) (.*)")


def fold(log: Path, t_scan: float, t_end: float) -> list[str]:
    """The exchange log between ``t_scan`` and ``t_end`` (epoch s), runs of polls and reads folded."""
    out: list[str] = []
    run: list | None = None  # [kind, first, last, count]

    def flush() -> None:
        if run is not None:
            out.append(f"{run[1]:8.3f} - {run[2]:7.3f}  {run[0]} x{run[3]}")

    for text in log.read_text().splitlines():
        m = LINE.match(text)
        if not m or m.group(2) == "Connection":
            continue
        t = dt.datetime.strptime(m.group(1), "%Y-%m-%dT%H:%M:%S.%f").replace(tzinfo=dt.UTC).timestamp() - t_scan
        if not -0.1 < t < t_end - t_scan + 0.2:
            continue
        msg = m.group(4)
        kind = ("buffer reads (FC03)" if " FC03 " in msg else "status polls" if "FC04 addr 200 " in msg
                else "window selects" if "FC16 addr 300 " in msg else None)
        if kind is not None:
            if run is not None and run[0] == kind and t - run[2] < 0.03:
                run[2], run[3] = t, run[3] + 1
                continue
            flush()
            run = [kind, t, t, 1]
            continue
        flush()
        run = None
        out.append(f"{t:8.3f}            {m.group(2)} {msg[:110]}")
    flush()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motors", type=int, default=1, help="counted motors after the warm-up (the last is shown)")
    ap.add_argument("--setup", default="default@500000", help="register map @ CAN bit rate")
    ap.add_argument("--profile", default="eol-default")
    ap.add_argument("--out", type=Path, default=None, help="keep the exchange log and the records here")
    args = ap.parse_args()

    from cli.fit import enable_jax_cache
    from eol_cal.dyno.mapfile import load_register_map
    from eol_cal.ecu import protocol as P
    from eol_cal.sim.loopback import loopback_line

    for name in ("pymodbus", "isotp", "UdsClient", "Connection", "can", "can_remote"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    from eol_cal.numerics.xla import configure_xla

    configure_xla()  # the simulators' plant in this process, as `eol-cal dyno-sim` and the demo run it
    enable_jax_cache()
    map_name, _, bitrate = args.setup.partition("@")
    with tempfile.TemporaryDirectory(prefix="trace-station-") as tmp_name:
        tmp = Path(tmp_name)
        out = args.out or tmp
        out.mkdir(parents=True, exist_ok=True)
        key = tmp / "key.hex"
        key.write_text(P.DEV_SECRET.hex())
        with loopback_line(tmp / "sim", register_map=load_register_map(map_name), realtime=True,
                           bitrate=int(bitrate)) as line:
            work = out / "work"  # the station's records, reports and captures: kept with --out
            work.mkdir(exist_ok=True)
            settings = bs.settings_file(work, line, map_name, key, args.profile)
            log = out / "exchanges.log"
            proc = subprocess.Popen(bs.eol_cal(bs.ROOT, "station", "--station", str(settings), "--operator", "bench",
                                               "--log-file", str(log)),
                                    cwd=bs.ROOT, env=bs.child_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                    stderr=subprocess.DEVNULL)
            screen = bs.Screen(proc)
            _, m = screen.wait_for(re.compile("Scan serial"), 0, 120)
            pos = m.end()
            try:
                for k in range(args.motors + 1):
                    serial = f"T{k:04d}"
                    line.load(serial, 1 + k)
                    t_scan, t0 = time.time(), time.monotonic()
                    proc.stdin.write(f"{serial}\n".encode())
                    proc.stdin.flush()
                    t_verdict, m = screen.wait_for(re.compile(rf"{serial}: (PASS|FAIL|ERROR)"), pos)
                    _, m = screen.wait_for(re.compile("Scan serial"), m.end())
                    pos = m.end()
                    rec = json.loads(bs.written(bs.run_dir(work / "reports", serial) / "report.json").read_text())
                    fig = bs.motor_figures(rec, serial, t_scan, t_scan + (t_verdict - t0), 0.0, bs.plant_late(line),
                                           bs.load(), 10000)
                    print(f"{serial}{' (warm-up)' if k == 0 else ''}: {fig.verdict}, critical path beyond physical "
                          f"{fig.critical:.2f} s, plant late {fig.plant_late:.2f} s", flush=True)
            finally:
                proc.stdin.write(b"q\n")
                proc.stdin.flush()
                proc.wait(60)
            captures = list(line.dyno.sim.captures)
        started = dt.datetime.fromisoformat(rec["started_at"]).timestamp()
        print(f"\n# {serial}: steps (s from the scan)")
        t = started
        for st in rec["steps"]:
            print(f"{t - t_scan:8.3f}  +{st['seconds'] or 0:.3f}  {st['step']}")
            t += st["seconds"] or 0.0
        print(f"\n# {serial}: the simulator's captures")
        for c in captures:
            source_s = (c.source_done or 0) - c.started
            print(f"capture {c.index}: {c.physical_end - c.started:.3f} s physical, source {source_s:.3f} s (late "
                  f"{c.source_late_s:.3f}), {c.computed} samples handed over early, {c.early_reads} early reads")
        print(f"\n# {serial}: exchanges (s from the scan)")
        print("\n".join(fold(log, t_scan, t_scan + (t_verdict - t0))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
