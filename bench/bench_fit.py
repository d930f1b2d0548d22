"""Speed of the ripple fit: warm time per capture, batched throughput, against scipy, and the CLI.

Each capture is 1 s at 20 kHz of one motor: 2 load points x 2 speeds, 0.25 s each (20000
samples), so c6, k6 and the delay are all identifiable from it. The alternative a user would
write is scipy.optimize.least_squares on the same model over every sample
(:mod:`eol_cal.analysis.fit.scipy_ref`); both run here on the same data, and the fits are compared.

    python bench/bench_fit.py [--captures 1000] [--scipy 5] [--cli] [--threads N]
    python bench/bench_fit.py --batch [--captures 400] [--chunk 100] [--rounds 1] [--baseline DIR ...]
    python bench/bench_fit.py --startup [--rounds 5] [--baseline DIR] [--same]

``--batch`` times the batched fit alone: ``fit_many`` in each mode (loop, map, vmap; inline and with
compression threads), captures/s (wall), CPU ms a capture (user + system of every thread) and the cores
used (CPU s / wall s), and the compression alone (``compress_many`` on 1 and 2 threads as ``fit_many``
queues it, and ``compress()`` a motor at a time), with the cores two GIL-free threads get at the start and
the end (:func:`free_cores`: whether two cores were free at all); each checkout (this one, then each
``--baseline DIR``, alternating ``--rounds`` times) in a process of its own on the same captures
(generated here, handed over in a file), its ``eol_cal`` imported from the checkout; the fits' k6, c6,
their phases and the delay compared with this checkout's (largest relative difference).

``--startup`` times the command line alone, from process start to its end: ``eol-cal --help``,
``eol-cal capture info`` and ``eol-cal fit`` (warm: its cache filled by a first run) on one 1 s
capture, wall and CPU (user + system) of each process, the rounds alternating this checkout and
``--baseline DIR``'s (``git worktree add DIR COMMIT``; its ``eol_cal`` and ``cli`` imported instead),
the median of the rounds; the fits' results are compared (numbers within 1e-12 relative; ``--same``: or
it fails; a baseline older than a change of the result's fields differs in them: the first difference is named).
"""

from __future__ import annotations

import os

# BLAS's own threads only spin on the fit's small products (and against the optional compression
# threads). Set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, default=1000)
    ap.add_argument("--scipy", type=int, default=5, help="captures fitted with scipy (it is slow)")
    ap.add_argument("--chunk", type=int, default=250)
    ap.add_argument("--cli", action="store_true", help="also time `eol-cal fit` on one capture file")
    ap.add_argument("--harmonics", default="6,12,18", help="orders fitted (eol-cal fit's default 6,12,18)")
    ap.add_argument("--threads", type=int, default=0, help="compression worker threads (fit_many's default 0: inline)")
    ap.add_argument("--startup", action="store_true", help="only the command line's start-up (see above)")
    ap.add_argument("--rounds", type=int, default=None, help="runs of each checkout (--startup: of each command, "
                    "default 5; --batch: default 1)")
    ap.add_argument("--baseline", action="append", default=[], help="a checkout of older code, side by side "
                    "(--startup: one; --batch: any number)")
    ap.add_argument("--batch", action="store_true", help="only the batched fit, side by side (see above)")
    ap.add_argument("--batch-worker", nargs=2, metavar=("NPZ", "JSON"), help=argparse.SUPPRESS)
    ap.add_argument("--same", action="store_true", help="--startup: fail unless the two checkouts' fits agree")
    args = ap.parse_args()
    if args.batch_worker:
        npz, out = args.batch_worker
        batch_worker(npz, out, chunk=args.chunk, harmonics=args.harmonics)
        return
    if args.startup:
        startup(args.rounds or 5, args.baseline[0] if args.baseline else None, args.same)
        return
    if args.batch:
        batch_side_by_side(args.captures, args.chunk, args.harmonics, args.rounds or 1, args.baseline)
        return

    import jax

    from eol_cal.analysis.fit import FitSpec, fit_many, fit_segments
    from eol_cal.analysis.fit.scipy_ref import fit_segments_scipy

    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}")
    t0 = time.perf_counter()
    motors = _captures(args.captures)
    n_samples = sum(len(a) for a in motors[0].theta)
    print(f"{args.captures} captures x {n_samples} samples generated in {time.perf_counter() - t0:.1f} s")
    spec = FitSpec(harmonics=tuple(int(h) for h in args.harmonics.split(",")))
    print(f"model: harmonics {spec.harmonics}, transducer {spec.transducer}, solver {spec.solver}")

    # warm time per capture, one at a time (compile first)
    fit_segments(motors[0], spec)
    times = []
    for m in motors[:50]:
        t0 = time.perf_counter()
        fit_segments(m, spec)
        times.append(time.perf_counter() - t0)
    warm = statistics.median(times)
    print(f"warm fit, one capture at a time: median {warm * 1e3:.2f} ms, p90 {np.percentile(times, 90) * 1e3:.2f} ms")

    rows = []
    threads = args.threads
    # fit_many compresses inline (0) or in `threads` workers ahead of the solve
    for mode, th in (("loop", threads), ("map", threads), ("vmap", threads), ("map", 1), ("map", 2)):
        fit_many(motors[: args.chunk], spec, mode=mode, chunk=args.chunk, threads=th)  # compile this shape
        t0 = time.perf_counter()
        fits = fit_many(motors, spec, mode=mode, chunk=args.chunk, threads=th)
        dt = time.perf_counter() - t0
        steps = [f.steps for f in fits]
        rows.append((f"{mode}, {th} thr", dt, len(motors) / dt, max(steps), float(np.mean(steps)),
                     all(f.converged for f in fits)))
    for name, dt, rate, smax, smean, ok in rows:
        print(f"batched {name:12s}: {dt:6.2f} s for {len(motors)} -> {rate:7.1f} captures/s "
              f"(steps mean {smean:.1f}, max {smax}; all converged: {ok})")

    # where the time goes: compression (numpy) vs the JAX solve + unpacking
    from concurrent.futures import ThreadPoolExecutor

    from eol_cal.analysis.fit import compress

    t0 = time.perf_counter()
    for m in motors[:200]:
        compress(m, spec)
    print(f"compression alone (1 thread): {(time.perf_counter() - t0) / len(motors[:200]) * 1e3:.2f} ms per capture")
    with ThreadPoolExecutor(2) as pool:
        t0 = time.perf_counter()
        list(pool.map(lambda m: compress(m, spec), motors[:400]))
    print(f"compression alone (2 threads): {(time.perf_counter() - t0) / len(motors[:400]) * 1e3:.2f} ms per capture (wall)")

    # scipy on the same model and data
    sc_times, dk = [], []
    fast = fit_many(motors[: args.scipy], spec, mode="loop")
    for m, f in zip(motors[: args.scipy], fast, strict=False):
        t0 = time.perf_counter()
        ref = fit_segments_scipy(m, spec)
        sc_times.append(time.perf_counter() - t0)
        dk.append(abs(ref["harmonics"][6]["k"][0] - f.harmonics[6]["k"].value) / f.harmonics[6]["k"].value)
    sc = statistics.mean(sc_times)
    best = max(r[2] for r in rows)
    print(f"scipy least_squares (trf, per-sample residual): {sc * 1e3:.0f} ms per capture -> {1 / sc:.2f} captures/s; "
          f"max |k6 difference| {max(dk):.1e} (relative)")
    print(f"throughput ratio, best batched JAX / scipy: {best * sc:.0f}x")

    if args.cli:
        from eol_cal.capture.io import write_capture
        from eol_cal.capture.synthetic import synthetic_capture

        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "one.csv")
            write_capture(synthetic_capture(rpm=600.0, i_qo=65.0, seconds=1.0, seed=1, serial="B-1"), path)
            env = dict(os.environ, EOL_CAL_JAX_CACHE=os.path.join(d, "jaxcache"))
            cmd = [sys.executable, "-m", "cli.main", "fit", path, "-o", os.path.join(d, "r.json"), "--no-c6",
                   "--delay", "0"]
            walls = []
            for _ in range(3):
                t0 = time.perf_counter()
                subprocess.run(cmd, env=env, check=False, capture_output=True)
                walls.append(time.perf_counter() - t0)
            print(f"`eol-cal fit` one 1 s capture, process start to JSON: cold cache {walls[0]:.2f} s, "
                  f"warm cache {min(walls[1:]):.2f} s")


#: the batched rows: (mode, compression threads (None: fit_many's default), ``fit_many``'s ``process``:
#: None its default, False the worker threads compressing in this process; a checkout without the
#: argument runs its default)
BATCH_ROWS: tuple[tuple[str, int | None, bool | None], ...] = (
    ("loop", 0, None), ("map", 0, None), ("vmap", 0, None), ("map", 1, None), ("map", 2, None), ("vmap", 1, None),
    ("vmap", 2, None), ("vmap", 1, False), ("vmap", None, None))
#: the row whose fits are compared across checkouts (fit_many's default for a batch)
DEFAULT_ROW = 8
#: the default row's mode and threads compressing in this process (this checkout's fits compared with it)
NO_PROCESS_ROW = 7
#: what the checkouts' fits are compared on
COMPARED = ("k6", "phase_k6", "c6", "phase_c6", "delay_s")


def _captures(n: int) -> list:
    """The batch's captures: 1 s at 20 kHz each, 2 loads x 2 speeds of 0.25 s, random k6, phase, delay."""
    from eol_cal.analysis.fit.synth import synthetic_segments

    rng = np.random.default_rng(7)
    return [synthetic_segments(rng, seg_s=0.25, fs_hz=20000.0, speeds_rpm=(300.0, 600.0), loads_a=(20.0, 65.0),
                               k6=rng.uniform(4e-4, 8e-4), phase_k6=rng.uniform(-3, 3), delay_s=rng.uniform(5e-5, 3e-4))[0]
            for _ in range(n)]


def batch_worker(npz: str, out: str, chunk: int, harmonics: str) -> None:
    """One checkout's batched rows on the captures of ``npz`` (written by :func:`batch_side_by_side`),
    its figures and fits to ``out`` (JSON)."""
    import json
    import resource

    import eol_cal
    from eol_cal.analysis.fit import FitSpec, SteadySegments, compress, fit_many

    data = np.load(npz)
    motors = [SteadySegments(theta=[data[f"{i}.theta.{s}"] for s in range(4)], t=[data[f"{i}.t.{s}"] for s in range(4)],
                             torque=[data[f"{i}.torque.{s}"] for s in range(4)], i_qo=data[f"{i}.i_qo"],
                             omega_e=data[f"{i}.omega_e"], pole_pairs=int(data["pole_pairs"]))
              for i in range(int(data["n"]))]
    spec = FitSpec(harmonics=tuple(int(h) for h in harmonics.split(",")))

    child: Any = None
    with contextlib.suppress(ImportError):  # a checkout without the compression process: None
        from eol_cal.analysis.fit import compress_process as child

    def cpu() -> float:
        """CPU s of this process and of its compression process (user + system)."""
        r = resource.getrusage(resource.RUSAGE_SELF)
        running = child.running() if child else None
        return r.ru_utime + r.ru_stime + (_process_cpu(running.pid) if running else 0.0)

    startup = None
    if child:  # started before the rows (once a process; a batch does not wait for it): its start timed here
        c0, t0 = cpu(), time.perf_counter()
        proc = child.compress_process()
        while proc and not proc.ready():
            time.sleep(0.001)
        startup = (time.perf_counter() - t0, cpu() - c0)
    rows, fits = [], []
    for mode, th, process in BATCH_ROWS:
        kw: dict[str, Any] = {} if child is None else dict(process=process)
        fit_many(motors[:chunk], spec, mode=mode, chunk=chunk, threads=th, **kw)  # compile this shape
        c0, t0 = cpu(), time.perf_counter()
        got = fit_many(motors, spec, mode=mode, chunk=chunk, threads=th, **kw)
        wall, used = time.perf_counter() - t0, cpu() - c0
        rows.append(dict(mode=mode, threads=th, rate=len(motors) / wall, cpu_ms=used / len(motors) * 1e3,
                         converged=all(f.converged for f in got)))
        fits.append([dict(k6=f.harmonics[6]["k"].value, phase_k6=f.harmonics[6]["k"].phase,
                          c6=f.harmonics[6]["c"].value, phase_c6=f.harmonics[6]["c"].phase, delay_s=f.delay_s)
                     for f in got])
    c0, t0 = cpu(), time.perf_counter()
    for m in motors:
        compress(m, spec)
    one = ((cpu() - c0) / len(motors) * 1e3, (time.perf_counter() - t0) / len(motors) * 1e3)
    Path(out).write_text(json.dumps(dict(code=os.path.dirname(os.path.dirname(eol_cal.__file__)), rows=rows,
                                         compress_ms=one, compress_rows=compress_rows(motors, spec, cpu),
                                         load=os.getloadavg()[0], fits=fits[DEFAULT_ROW], startup=startup,
                                         threads_fits=fits[NO_PROCESS_ROW])))


def _process_cpu(pid: int) -> float:
    """CPU s (user + system) of process ``pid`` so far (Linux's /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def compress_rows(motors: list, spec: Any, cpu: Any) -> list[dict] | None:
    """The compression alone as ``fit_many`` queues it (16 motors a ``compress_many`` call), on 1 and
    2 threads: captures/s (wall), CPU ms a capture; None for a checkout without ``compress_many``."""
    from concurrent.futures import ThreadPoolExecutor

    try:
        from eol_cal.analysis.fit.compression import compress_many
    except ImportError:
        return None
    blocks = [motors[a : a + 16] for a in range(0, len(motors), 16)]
    S = max(m.n_segments for m in motors)
    rows = []
    for threads in (1, 2):
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(lambda b: compress_many(b, spec, S), blocks[:threads]))  # each thread's buffers
            c0, t0 = cpu(), time.perf_counter()
            list(pool.map(lambda b: compress_many(b, spec, S), blocks))
            wall, used = time.perf_counter() - t0, cpu() - c0
        rows.append(dict(threads=threads, rate=len(motors) / wall, cpu_ms=used / len(motors) * 1e3))
    return rows


def batch_side_by_side(captures: int, chunk: int, harmonics: str, rounds: int, baselines: list[str]) -> None:
    """The batched fit of this checkout and each baseline's, alternating, each in its own process."""
    import json

    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    codes = {"this": here, **{f"base{i}": os.path.abspath(b) for i, b in enumerate(baselines)}}
    with tempfile.TemporaryDirectory() as d:
        npz = os.path.join(d, "captures.npz")
        motors = _captures(captures)
        arrays: dict[str, Any] = {"n": np.array(len(motors)), "pole_pairs": np.array(motors[0].pole_pairs)}
        for i, m in enumerate(motors):
            arrays.update({f"{i}.i_qo": m.i_qo, f"{i}.omega_e": m.omega_e})
            for s in range(m.n_segments):
                arrays.update({f"{i}.theta.{s}": m.theta[s], f"{i}.t.{s}": m.t[s], f"{i}.torque.{s}": m.torque[s]})
        np.savez(npz, **arrays)
        print(f"{captures} captures x 20000 samples, chunk {chunk}, harmonics {harmonics}; "
              f"{len(os.sched_getaffinity(0))} cores, load at start {os.getloadavg()[0]:.1f}, "
              f"two GIL-free threads get {free_cores():.2f} cores", flush=True)
        got: dict[str, list[dict]] = {}
        for _ in range(rounds):
            for name, code in codes.items():
                out = os.path.join(d, f"{name}.json")
                # bytecode under the run's own prefix: nothing is written into a checkout
                env = dict(os.environ, PYTHONPATH=code, PYTHONPYCACHEPREFIX=os.path.join(d, f"pycache-{name}"))
                subprocess.run([sys.executable, os.path.abspath(__file__), "--batch-worker", npz, out, "--chunk", str(chunk),
                                "--harmonics", harmonics], env=env, check=True)
                got.setdefault(name, []).append(json.loads(Path(out).read_text()))
        print(f"load at end {os.getloadavg()[0]:.1f}, two GIL-free threads get {free_cores():.2f} cores; best of {rounds} "
              "round(s) a row (captures/s wall; CPU ms a capture, the least; cores used: CPU s / wall s of the best round)")
        print(f"{'row':<22}" + "".join(f"{name + ' (' + runs[0]['code'][-14:] + ')':>42}" for name, runs in got.items()))
        for r, (mode, th, process) in enumerate(BATCH_ROWS):
            cells = [_cell([x["rows"][r] for x in runs]) for runs in got.values()]
            name = f"{mode}, {'default' if th is None else th} thr" + (", no proc" if process is False else "")
            print(f"{name:<22}" + "".join(f"{c:>42}" for c in cells))
        for r, th in enumerate((1, 2)):
            cells = [_cell([x["compress_rows"][r] for x in runs]) if runs[0].get("compress_rows") else "-"
                     for runs in got.values()]
            print(f"{'compress, ' + str(th) + ' thr':<22}" + "".join(f"{c:>42}" for c in cells))
        print(f"{'compress()':<22}" + "".join(
            f"{min(x['compress_ms'][0] for x in runs):>30.3f} ms CPU a capture" for runs in got.values()))
        for name, runs in got.items():
            if runs[0].get("startup"):
                print(f"{name}: the compression process's start, to its imports done (once a process): wall "
                      + ", ".join(f"{x['startup'][0]:.3f}" for x in runs) + " s, CPU "
                      + ", ".join(f"{x['startup'][1]:.3f}" for x in runs) + " s (this and the child)")
        ref = got["this"][0]["fits"]
        worst = {k: max(abs(a[k] - b[k]) / max(abs(a[k]), 1e-300) for a, b in zip(ref, got["this"][0]["threads_fits"],
                                                                                  strict=True)) for k in COMPARED}
        print("fits of this, the default row (vmap, default thr) against its no-process row: largest relative difference "
              + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
        for name, runs in got.items():
            if name != "this":
                worst = {k: max(abs(a[k] - b[k]) / max(abs(a[k]), 1e-300) for a, b in zip(ref, runs[0]["fits"], strict=True))
                         for k in COMPARED}
                print(f"fits of {name} against this: largest relative difference "
                      + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))


def free_cores(seconds: float = 0.5) -> float:
    """The cores this process gets now: CPU s / wall s of two threads of a numpy kernel that releases
    the GIL (``np.sin`` on 64k doubles). The load average does not say it: the kernel shares the
    cores among sessions (autogroups), so at load 3 one busy session beside leaves this one core."""
    import resource
    import threading

    x = np.linspace(0.0, 1.0, 1 << 16)

    def spin() -> None:
        out, end = np.empty_like(x), time.perf_counter() + seconds
        while time.perf_counter() < end:
            np.sin(x, out=out)

    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    threads = [threading.Thread(target=spin) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return (r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime) / (time.perf_counter() - t0)


def _cell(runs: list[dict]) -> str:
    """One checkout's figures of one row over its rounds: the best rate, the least CPU ms a capture,
    the cores the best round used."""
    best = max(runs, key=lambda x: x["rate"])
    return (f"{best['rate']:8.1f}/s {min(x['cpu_ms'] for x in runs):6.3f} ms {best['rate'] * best['cpu_ms'] / 1e3:4.2f} cores"
            + ("" if best.get("converged", True) else " NOT CONVERGED"))


def _run(code: str, args: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, CPU s) of ``python -m cli.main ARGS`` with the code of checkout ``code``."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "cli.main", *args], env=dict(env, PYTHONPATH=code), cwd=code,
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise SystemExit(f"{code}: eol-cal {' '.join(args)} failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def startup(rounds: int, baseline: str | None, same: bool = False) -> None:
    """The command line's start-up, this checkout against ``baseline`` (module docstring); ``same``:
    fail when the two fits differ."""
    import json

    from eol_cal.capture.io import write_capture
    from eol_cal.capture.synthetic import synthetic_capture

    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    codes = {"this": here, **({"baseline": os.path.abspath(baseline)} if baseline else {})}
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "one.csv")
        write_capture(synthetic_capture(rpm=600.0, i_qo=65.0, seconds=1.0, seed=1, serial="B-1"), path)
        commands = {"--help": ["--help"], "capture info": ["capture", "info", path],
                    "fit (warm)": ["fit", path, "--no-c6", "--delay", "0"]}
        # every checkout's bytecode (and the libraries') under one prefix of the run's own: none is
        # compiled again per run (PYTHONDONTWRITEBYTECODE would), nothing is written into a checkout
        base = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        envs = {name: dict(base, EOL_CAL_JAX_CACHE=os.path.join(d, f"cache-{name}"),
                           PYTHONPYCACHEPREFIX=os.path.join(d, f"pycache-{name}")) for name in codes}
        for name, code in codes.items():  # fill each checkout's cache, and compile its modules
            for args in commands.values():
                _run(code, [*args, "-o", os.path.join(d, f"{name}.json")] if args[0] == "fit" else args, envs[name])
        print(f"cores: {len(os.sched_getaffinity(0))}, load at start {os.getloadavg()[0]:.1f}", flush=True)
        got: dict[tuple[str, str], list[tuple[float, float]]] = {}
        for _ in range(rounds):
            for cmd, args in commands.items():
                for name, code in codes.items():
                    out = [*args, "-o", os.path.join(d, f"{name}.json")] if args[0] == "fit" else args
                    got.setdefault((cmd, name), []).append(_run(code, out, envs[name]))
        print(f"load at end {os.getloadavg()[0]:.1f}; median of {rounds} runs, process start to end")
        print(f"{'command':<16}{'checkout':<10}{'wall s':>8}{'cpu s':>8}")
        for (cmd, name), rows in got.items():
            wall, cpu = statistics.median(r[0] for r in rows), statistics.median(r[1] for r in rows)
            print(f"{cmd:<16}{name:<10}{wall:>8.2f}{cpu:>8.2f}")
        if baseline:
            docs = [json.loads(Path(d, f"{name}.json").read_text())["motors"] for name in codes]
            worst = max_relative_difference(docs[0], docs[1])
            if worst <= 1e-12:  # tests/test_fit_typed.py's tolerance
                print(f"the fits' motors: the same keys, strings and nulls; numbers within {worst:.1e} relative")
            else:
                # an older baseline may write other fields (what it did not have yet): said, not fatal
                # unless asked for
                print(f"the fits' motors differ: first at {first_difference(docs[0], docs[1])}")
                if same:
                    raise SystemExit("the fits differ")


def first_difference(a: object, b: object, path: str = "motors") -> str:
    """Where two parsed JSON documents first differ beyond 1e-12 relative (a key path), "" if nowhere."""
    if isinstance(a, dict) and isinstance(b, dict):
        if list(a) != list(b):
            return f"{path}: keys {sorted(set(a) ^ set(b))}"
        return next((w for k in a if (w := first_difference(a[k], b[k], f"{path}.{k}"))), "")
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path}: {len(a)} against {len(b)} entries"
        return next((w for i, (x, y) in enumerate(zip(a, b, strict=True)) if (w := first_difference(x, y, f"{path}[{i}]"))), "")
    return "" if max_relative_difference(a, b) <= 1e-12 else f"{path}: {a!r} against {b!r}"


def max_relative_difference(a: object, b: object) -> float:
    """The largest relative difference between the numbers of two parsed JSON documents; inf when
    anything else differs (keys, strings, nulls, lengths)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return max((max_relative_difference(a[k], b[k]) for k in a), default=0.0) if list(a) == list(b) else float("inf")
    if isinstance(a, list) and isinstance(b, list):
        return max(map(max_relative_difference, a, b), default=0.0) if len(a) == len(b) else float("inf")
    if isinstance(a, float) and isinstance(b, float):
        return 0.0 if a == b else abs(a - b) / max(abs(a), abs(b))
    return 0.0 if a == b else float("inf")


if __name__ == "__main__":
    main()
