"""Modbus capture transfer rate: registers/s and samples/s, ours against the plain way.

The dyno simulator runs as its own process (``eol-cal dyno-sim --source synthetic``), as a real
dyno would be another machine; it records one capture, then the same buffer is read

- plain: one pymodbus ``ModbusTcpClient``, one ``read_holding_registers`` of 125 registers after
  the other (what a user writes first);
- ours: :meth:`eol_cal.dyno.client.DynoClient.read_buffer`, which overlaps the 125-register reads
  over several TCP connections (``connections`` = 1, 2, 4, 8; 4 is the default).

Both read the same pages (page select + window reads) and are checked to return identical words.
``client CPU s`` is this process's CPU for the read, ``dyno CPU s`` the simulator process's for
serving it; the last row is
:data:`STATUS_POLLS` status reads (:meth:`~eol_cal.dyno.client.DynoClient.status`, the station's poll while
the shaft turns) one after the other. Then the end-to-end time of ``eol-cal acquire`` on the default profile is taken,
against the synthetic source and against the plant (compiled at simulator start-up).

``--baseline DIR``: the reads with this checkout's code and with another checkout's (``git
worktree add DIR COMMIT``: its simulator and its ``eol_cal``), each in a process of its own,
alternated ``--rounds`` times (the machine's speed moves between runs); then the medians over
the rounds side by side.

    python bench/bench_dyno.py [--samples 100000] [--repeat 3] [--no-plant] [--baseline DIR [--rounds 3]]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

from eol_cal.dyno import registers as rm
from eol_cal.dyno.client import DynoClient
from eol_cal.dyno.setpoints import DynoSetpoint
from eol_cal.dyno.transfer import DynoConfig
from eol_cal.dyno.mapfile import default_register_map

ROOT = Path(__file__).resolve().parents[1]
#: status reads timed one after the other (the table's last row)
STATUS_POLLS = 2000


def cpu_of(proc: psutil.Process) -> float:
    t = proc.cpu_times()
    return t.user + t.system


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def plain_read(host: str, port: int, channel_ids: list[int], n: int) -> tuple[dict[int, np.ndarray], int]:
    """The plain way: one synchronous 125-register read after the other on one connection."""
    from pymodbus.client import ModbusTcpClient

    m = default_register_map()
    c = ModbusTcpClient(host, port=port, timeout=2.0, retries=0)
    c.connect()
    out, regs = {}, 0
    for cid in channel_ids:
        per = m.regs_per_sample(cid)
        page_samples = m.samples_per_page(cid)
        parts = []
        for first in range(0, n, page_samples):
            c.write_registers(m["buf_channel"].address, [cid] + m.encode("buf_offset", first), device_id=1)
            n_regs = min(page_samples, n - first) * per
            for address, cnt in m.page_blocks(n_regs):
                r = c.read_holding_registers(address, count=cnt, device_id=1)
                assert not r.isError(), r
                parts.append(np.asarray(r.registers, dtype=np.uint16))
                regs += cnt
        out[cid] = np.concatenate(parts)
    c.close()
    return out, regs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=100_000, help="capture length (samples at 20 kHz)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-plant", dest="plant", action="store_false", help="skip the acquire against the plant-backed simulator")
    ap.add_argument("--baseline", type=Path, help="another checkout: its reads too, alternated with this one's")
    ap.add_argument("--rounds", type=int, default=3, help="with --baseline: the alternations")
    ap.add_argument("--code", type=Path, default=ROOT, help=argparse.SUPPRESS)
    ap.add_argument("--json", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    import eol_cal

    print(f"code: {Path(eol_cal.__file__).resolve().parents[1]}")
    if args.baseline is None:
        rows = reads(args, args.code)
        if args.json is not None:
            args.json.write_text(json.dumps(rows))
    else:
        compare(args)
    if args.plant:
        codes = {"this checkout": args.code}
        if args.baseline is not None:
            codes[str(args.baseline)] = args.baseline.resolve()
        sim_cpu: dict[str, list[float]] = {name: [] for name in codes}
        for _ in range(args.rounds if args.baseline is not None else 1):
            for name, code in codes.items():
                print(f"{name}:", end="")
                sim_cpu[name].append(plant_acquire(code))
        if args.baseline is not None:
            print("the plant-backed simulator's CPU s for two acquires, median of the rounds: "
                  + ", ".join(f"{name} {statistics.median(v):.2f}" for name, v in sim_cpu.items()))
    return 0


def compare(args: argparse.Namespace) -> None:
    """This checkout's reads and the baseline's, alternated; the medians side by side."""
    codes = {"this checkout": ROOT, str(args.baseline): args.baseline.resolve()}
    got: dict[str, list[list]] = {name: [] for name in codes}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rows.json"
        for r in range(args.rounds):
            for name, code in codes.items():
                print(f"\nround {r + 1}, {name}:", flush=True)
                subprocess.run([sys.executable, __file__, "--samples", str(args.samples), "--repeat", str(args.repeat),
                                "--no-plant", "--code", str(code), "--json", str(out)], check=True, cwd=code,
                               env={**os.environ, "PYTHONPATH": str(code)})
                got[name].append(json.loads(out.read_text()))
    print(f"\nmedians of {args.rounds} alternated rounds: wall s / client CPU s / dyno CPU s")
    print(f"{'method':<34}" + "".join(f"{name[-26:]:>28}" for name in codes))
    for i, (label, *_) in enumerate(got["this checkout"][0]):
        cells = []
        for name in codes:
            wall, cpu, dyno = (statistics.median(rounds[i][j] for rounds in got[name]) for j in (1, 2, 3))
            cells.append(f"{wall:.2f} / {cpu:.2f} / {dyno:.2f}")
        print(f"{label:<34}" + "".join(f"{c:>28}" for c in cells))


def reads(args: argparse.Namespace, root: Path) -> list[tuple[str, float, float, float]]:
    """The buffer read the plain way and ours, on the synthetic simulator of the checkout ``root``:
    each method's (label, median wall s, client CPU s, dyno CPU s)."""

    host, port = "127.0.0.1", free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    server = subprocess.Popen(
        [sys.executable, "-m", "cli.main", "dyno-sim", "--listen", f"{host}:{port}", "--source", "synthetic"],
        stderr=subprocess.PIPE, text=True, env={**env, "PYTHONPATH": str(root)}, cwd=root)
    dyno = psutil.Process(server.pid)
    try:
        server.stderr.readline()
        cfg = DynoConfig(host=host, port=port, timeout=2.0)
        dc = DynoClient(cfg)
        dc.connect()
        dc.set_point(DynoSetpoint(60.0, args.samples / 20000, iq=65.0, ramp_rpm_s=5000.0))
        st = dc.capture(args.samples, 20000)
        m = default_register_map()
        names = [name for cid, name in m.analog_channels.items() if int(st["capture_channels"]) & rm.channel_bit(cid)]
        ids = [cid for cid, name in m.analog_channels.items() if name in names] + [m.window.digital_id]
        regs_per_sample = 2 * len(names) + 1
        total_regs = args.samples * regs_per_sample
        print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load avg {os.getloadavg()[0]:.1f}; "
              f"python {platform.python_version()}")
        print(f"capture: {args.samples} samples x ({', '.join(names)} as f32 + digital u16) = "
              f"{regs_per_sample} registers/sample, "
              f"{total_regs} registers; dyno simulator in its own process on {host}")
        print(f"{'method':<34}{'median s':>10}{'registers/s':>14}{'samples/s':>12}{'x plain':>9}{'client CPU s':>13}"
              f"{'dyno CPU s':>11}")
        ref = None
        rows = []
        times, cpus, served = [], [], []
        for _ in range(args.repeat):
            t0, c0, d0 = time.perf_counter(), time.process_time(), cpu_of(dyno)
            words, regs = plain_read(host, port, ids, args.samples)
            times.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            served.append(cpu_of(dyno) - d0)
            assert regs == total_regs
        ref = words
        plain_s = statistics.median(times)
        rows.append(("plain: 1 connection, sequential", plain_s, statistics.median(cpus), statistics.median(served)))
        for k in (1, 2, 4, 8):
            dk = DynoClient(DynoConfig(host=host, port=port, timeout=2.0, connections=k))
            times, cpus, served = [], [], []
            for _ in range(args.repeat):
                t0, c0, d0 = time.perf_counter(), time.process_time(), cpu_of(dyno)
                got = dk.read_buffer(names, args.samples)
                times.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
                served.append(cpu_of(dyno) - d0)
            for cid, name in m.analog_channels.items():
                if name in names:
                    np.testing.assert_array_equal(got[name], m.words_to_analog(ref[cid]))
            a, b, h = m.unpack_digital(ref[m.window.digital_id])
            np.testing.assert_array_equal(got["hall"], h)
            dk.close()
            rows.append((f"ours: {k} parallel connection{'s' if k > 1 else ''}", statistics.median(times),
                         statistics.median(cpus), statistics.median(served)))
        for label, s, cpu, dyno_cpu in rows:
            print(f"{label:<34}{s:>10.3f}{total_regs / s:>14,.0f}{args.samples / s:>12,.0f}{plain_s / s:>9.2f}{cpu:>13.2f}"
                  f"{dyno_cpu:>11.2f}")
        # what a station's client does ~100 times a second while the shaft turns: read the status block
        for _ in range(100):
            dc.status()
        t0, c0, d0 = time.perf_counter(), time.process_time(), cpu_of(dyno)
        for _ in range(STATUS_POLLS):
            dc.status()
        rows.append((f"status: {STATUS_POLLS} polls", time.perf_counter() - t0, time.process_time() - c0,
                     cpu_of(dyno) - d0))
        print(f"{rows[-1][0]:<34}{rows[-1][1]:>10.3f}{'':>44}{rows[-1][2]:>13.2f}{rows[-1][3]:>11.2f}")
        dc.safe_state()
        dc.close()

        if args.json is None:
            print("eol-cal acquire --profile eol-default (8 segments, 7.7 s of capture at 10 kHz), whole process:")
            print(f"  synthetic source: {acquire_wall(host, port, env, root):.2f} s wall", flush=True)
    finally:
        server.terminate()
        server.wait(10)
    return rows


def plant_acquire(root: Path) -> float:
    """``eol-cal acquire`` twice against the plant-backed simulator of the checkout ``root``; the
    simulator's CPU s for the two (its start and the plant's compiling not counted)."""
    host, port = "127.0.0.1", free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    server = subprocess.Popen(
        [sys.executable, "-m", "cli.main", "dyno-sim", "--listen", f"{host}:{port}", "--source", "plant"],
        stderr=subprocess.PIPE, text=True, env={**env, "PYTHONPATH": str(root)}, cwd=root)
    dyno = psutil.Process(server.pid)
    try:
        server.stderr.readline()
        ready = server.stderr.readline().strip()  # "plant ready (N s)": compiled before the first capture
        c0 = cpu_of(dyno)
        walls = [acquire_wall(host, port, env, root) for _ in range(2)]
        spent = cpu_of(dyno) - c0
        print(f"  plant source ({ready}): {walls[0]:.2f} s wall, again: {walls[1]:.2f} s wall; "
              f"the simulator {spent:.2f} CPU s", flush=True)
        return spent
    finally:
        server.terminate()
        server.wait(10)


def acquire_wall(host: str, port: int, env: dict, root: Path) -> float:
    """Wall time (s) of one ``eol-cal acquire`` process on the default profile."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "cap.mf4"
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "cli.main", "acquire", "--dyno", f"{host}:{port}", "-o", str(out)],
                           capture_output=True, text=True, env={**env, "PYTHONPATH": str(root)}, cwd=root)
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            raise SystemExit(f"acquire failed: {r.stderr}")
    return wall


if __name__ == "__main__":
    sys.exit(main())
