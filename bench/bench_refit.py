"""Lot refit throughput: one process and Dask distributed with 1 and 2 local workers, against
merely reading the same files, and against an older checkout of the code, over one synthetic lot
(one directory of six captures per serial).

    python bench/bench_refit.py [--serials 400] [--rounds 2] [--baseline DIR]
    python bench/bench_refit.py --stages [--serials 24]    # CPU a serial by stage, this process


Every alternative runs in a fresh process of its own (``--child``), prepared as `eol-cal refit`
prepares its workers (:func:`eol_cal.lot.cluster.prepare_fit_process`) and warm (a batch of
serials outside the lot, on every worker, before the clock); the rounds alternate them, so a
change in the machine's load falls on all of them. ``cpu/serial`` is the CPU time (user +
system) of the child and everything it started (nannies, workers), which other jobs on the
machine move much less than the wall time; ``sys/serial`` its system part and ``switches/serial``
the voluntary context switches (a thread that waits: for the GIL, for a lock, for the disk).

- ``read_capture``: every capture read as the refit reads it (structure check, decode, channel
  map, validation), nothing else: the time to merely read and decode the files;
- ``asammdf``: every capture decoded with plain asammdf (``MDF(path).select`` of every channel):
  what reading the files costs with the library alone;
- ``loop``: the refit in one process, one thread (:func:`eol_cal.lot.refit.refit_batches`, batches
  of :data:`~eol_cal.lot.refit.REFIT_BATCH` serials, each read and its estimator runs started before
  the batch ahead is fitted; an older checkout without it: :func:`~eol_cal.lot.refit.refit_serials`
  of one batch after the other);
- ``threads``: the refit in one process on both cores (:func:`eol_cal.lot.refit.refit_in_process`:
  the same batches on :data:`THREADS` threads, whatever its default); ``cores`` is its CPU time
  over its wall time. The one-process figure (the targets' line) is the row of
  :func:`~eol_cal.lot.refit.refit_in_process`'s default (:data:`~eol_cal.lot.refit.REFIT_THREADS`:
  one thread, the loop's row);
- ``dask, N workers``: :func:`eol_cal.lot.refit.refit_lot` on the cluster `eol-cal refit` starts;
- ``--baseline DIR``: the loop and the 2-worker cluster once more with the code of another
  checkout (``git worktree add DIR COMMIT``), its ``eol_cal`` imported instead of this one.

All refits must give the same k6, c6, R^2 and RMS per serial (checked); the phases may differ
by float32 rounding of the firmware frame (the largest difference is printed).

``--stages``: the loop's CPU time a serial by stage (:data:`STAGES`: the library's functions
wrapped with a counter of the calling thread's CPU time, so no profiler's overhead; what JAX's own
thread computes meanwhile, the estimator's ticks started ahead, is in the whole refit's line, the
process's CPU time, and in no stage), over a batch outside the lot
(the first in the process: it traces and loads the programs), the lot (a first pass) and the
same lot again (a second pass). A stage indented under another is part of it. With
``PYTHONPATH=DIR`` the code of another checkout is measured (this file's wrappers, its functions).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

POINTS = [(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]
HERE = Path(__file__).resolve()
FIGURES = ("k6", "c6", "r2", "rms")
#: threads of the ``threads`` alternative: the machine's two cores
THREADS = 2
#: a baseline whose float path differs in the last bits (the batched compression's products, issue 37)
#: agrees to this relative difference (tests/test_fit_typed.py's tolerance); a changed result does not
SAME_REL = 1e-12
#: a child's CPU s (user + system), system CPU s and voluntary context switches (:func:`_tree_cpu`)
Counters = tuple[float, float, float]
#: the refit's stages (``--stages``): (label, module, function); the function is looked up in that
#: module at call time by its callers (a lazy import, or a name of that module's own)
STAGES = (
    ("read and decode", "eol_cal.capture.io", "read_capture"),
    ("segments (angle, halls)", "eol_cal.analysis.fit.capture", "segment_motors"),
    ("firmware frame", "eol_cal.analysis.fit.capture", "measure_firmware_frames"),
    ("  estimator", "eol_cal.analysis.fit.capture", "firmware_frame_parts"),
    ("estimator started ahead (its ticks on JAX's thread)", "eol_cal.analysis.fit.capture", "start_firmware_frames"),
    ("  fingerprint, angle correction", "eol_cal.analysis.fit.capture", "measure_fingerprint"),
    ("joint fit (compression, solver)", "eol_cal.analysis.fit", "fit_many"),
    ("noise at the harmonics (intervals, model check)", "eol_cal.analysis.fit.segment_noise", "segment_noise"),
    ("model check", "eol_cal.analysis.fit.model_check", "check_model"),
    ("  speed bands' fits", "eol_cal.analysis.fit.model_check", "fit_many"),
    ("  sees_up_to_hz", "eol_cal.analysis.fit.model_check", "sees_up_to_hz"),
    ("mechanical fit", "eol_cal.analysis.fit.mech_orders", "fit_mech"),
    ("  split_noise", "eol_cal.analysis.fingerprint", "split_noise"),
    ("  orders", "eol_cal.analysis.fit.mech_orders", "fit_orders"),
    ("result record (motor_result)", "eol_cal.analysis.result", "motor_result"),
)


def make_lot(d: Path, n: int, first: int = 0) -> list[list[Path]]:
    from eol_cal.capture.io import write_capture
    from eol_cal.capture.synthetic import synthetic_capture

    groups = []
    for i in range(first, first + n):
        sd = d / f"S{i:04d}"
        sd.mkdir()
        g = []
        for j, (rpm, iq) in enumerate(POINTS):
            c = synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=100 * i + j, theta_r0=0.7 * j,
                                  k6=0.0006 + 1e-6 * (i % 50), serial=f"S{i:04d}")
            write_capture(c, sd / f"c{j}.mf4")
            g.append(sd / f"c{j}.mf4")
        groups.append(g)
    return groups


def _groups(d: Path) -> list[list[Path]]:
    return [sorted(p.glob("*.mf4")) for p in sorted(d.iterdir())]


def _tree_cpu() -> Counters:
    """CPU seconds (user + system), system CPU seconds and voluntary context switches of this
    process (every thread it ran, ended ones too) and all its descendants alive now (their
    threads alive now). A switch is a thread that waited: for the GIL, a lock, the disk."""
    import resource

    import psutil

    me = resource.getrusage(resource.RUSAGE_SELF)
    total = [me.ru_utime + me.ru_stime, me.ru_stime, float(me.ru_nvcsw)]
    for p in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.Error, OSError):
            t = p.cpu_times()
            total[0] += t.user + t.system
            total[1] += t.system
            for status in Path(f"/proc/{p.pid}/task").glob("*/status"):
                line = next(x for x in status.read_text().splitlines() if x.startswith("voluntary_ctxt_switches"))
                total[2] += float(line.split()[1])
    return total[0], total[1], total[2]


def _spent(c0: Counters) -> Counters:
    """:func:`_tree_cpu`'s counters since ``c0``."""
    c1 = _tree_cpu()
    return c1[0] - c0[0], c1[1] - c0[1], c1[2] - c0[2]


# ------------------------------------------------------------------------------------------
# the children: one alternative each, in a fresh process


def _rows_of(refit: Any, groups: list[list[Path]], **kw: Any) -> list[dict[str, Any]]:
    """Rows of a lot in one process, one thread: batches, each read and its estimator started
    before the one ahead is fitted, where the code has it (:func:`eol_cal.lot.refit.refit_batches`);
    else batches one after the other; else serial by serial."""
    if hasattr(refit, "refit_batches"):
        b = refit.REFIT_BATCH
        return [r for rows in refit.refit_batches((groups[k:k + b] for k in range(0, len(groups), b)), **kw)
                for r in rows]
    if hasattr(refit, "refit_serials"):
        b = refit.REFIT_BATCH
        return [r for k in range(0, len(groups), b) for r in refit.refit_serials(groups[k:k + b], **kw)]
    return [refit.refit_capture(g, **kw) for g in groups]


def _child_read(lot: list[list[Path]], plain_asammdf: bool) -> tuple[list[Any], float, Counters]:
    import eol_cal.analysis.fit.motors  # noqa: F401 - the same process as a refit's, JAX loaded
    from eol_cal.capture.io import read_capture

    def asammdf_read(p: Path) -> int:
        from asammdf import MDF

        mdf = MDF(str(p))
        try:
            req = [(None, gi, ci) for gi, g in enumerate(mdf.groups) for ci in range(len(g.channels))
                   if ci != mdf.masters_db.get(gi)]
            return sum(len(s.samples) for s in mdf.select(req))
        finally:
            mdf.close()

    read = asammdf_read if plain_asammdf else read_capture
    for p in lot[0]:
        read(p)
    c0, t0 = _tree_cpu(), time.perf_counter()
    for g in lot:
        for p in g:
            read(p)
    return [], time.perf_counter() - t0, _spent(c0)


def _child_loop(lot: list[list[Path]], warm: list[list[Path]], threads: bool) -> tuple[list[Any], float, Counters]:
    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot import refit
    from eol_cal.lot.cluster import prepare_fit_process

    cache = default_cache_dir()
    prepare_fit_process(cache)
    _rows_of(refit, warm, bench="none", cache_dir=cache)
    c0, t0 = _tree_cpu(), time.perf_counter()
    if threads:
        rows = refit.refit_in_process(lot, bench="none", cache_dir=cache, threads=THREADS)
    else:
        rows = _rows_of(refit, lot, bench="none", cache_dir=cache)
    return rows, time.perf_counter() - t0, _spent(c0)


def _child_dask(lot: list[list[Path]], warm: list[list[Path]], n: int) -> tuple[list[Any], float, Counters]:
    from distributed import Client, wait

    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot import refit
    from eol_cal.lot.cluster import RefitWorkerSetup, local_cluster

    cache = default_cache_dir()
    warm_args = [[str(q) for q in g] for g in warm]
    with local_cluster(n) as cluster, Client(cluster) as client:
        client.register_plugin(RefitWorkerSetup(cache))
        task = (refit.refit_serials, warm_args) if hasattr(refit, "refit_serials") else (refit.refit_capture, warm_args[0])
        wait([client.submit(*task, bench="none", cache_dir=str(cache), pure=False, workers=[addr],
                            allow_other_workers=False) for addr in client.scheduler_info()["workers"]])
        c0, t0 = _tree_cpu(), time.perf_counter()
        rows = refit.refit_lot(lot, client, bench="none", cache_dir=cache)
        return rows, time.perf_counter() - t0, _spent(c0)


def child(name: str, lot_dir: Path, warm_dir: Path, out: Path) -> None:
    lot, warm = _groups(lot_dir), _groups(warm_dir)
    if name in ("read_capture", "asammdf"):
        rows, wall, cpu = _child_read(lot, name == "asammdf")
    elif name in ("loop", "threads"):
        rows, wall, cpu = _child_loop(lot, warm, name == "threads")
    else:
        rows, wall, cpu = _child_dask(lot, warm, int(name.split("-")[1]))
    bad = [r["error"] for r in rows if r["error"]]
    if bad:
        raise RuntimeError(bad[0])
    figures = [{k: r[k] for k in ("serial", "phase_k6", *FIGURES)} for r in rows]
    out.write_text(json.dumps({"wall": wall, "cpu": cpu, "rows": figures}))


def stages(serials: int) -> None:
    """``--stages``: CPU ms a serial by stage (:data:`STAGES`), warm-up batch, first and second pass."""
    import functools
    import importlib

    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.lot import refit
    from eol_cal.lot.cluster import prepare_fit_process

    cpu: dict[str, float] = {}

    def counted(label: str, f: Any) -> Any:
        @functools.wraps(f)
        def w(*args: Any, **kw: Any) -> Any:
            c = time.thread_time()
            try:
                return f(*args, **kw)
            finally:
                cpu[label] = cpu.get(label, 0.0) + time.thread_time() - c
        return w

    for label, module, name in STAGES:
        try:
            m = importlib.import_module(module)
        except ModuleNotFoundError:  # older code may lack a stage's module
            continue
        if hasattr(m, name):  # or its function
            setattr(m, name, counted(label, getattr(m, name)))
    cache = default_cache_dir()
    prepare_fit_process(cache)
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "lot").mkdir()
        (Path(d) / "warm").mkdir()
        make_lot(Path(d) / "lot", serials)
        make_lot(Path(d) / "warm", refit.REFIT_BATCH, first=serials)
        passes = [("warm-up batch", _groups(Path(d) / "warm")), ("first pass", _groups(Path(d) / "lot")),
                  ("second pass", _groups(Path(d) / "lot"))]
        table: dict[str, list[float]] = {label: [] for label, _, _ in STAGES}
        totals, rows0 = [], None
        for _, lot in passes:
            cpu.clear()
            c0 = time.process_time()
            rows = _rows_of(refit, lot, bench="none", cache_dir=cache)
            totals.append((time.process_time() - c0) / len(lot) * 1e3)
            if any(r["error"] for r in rows):
                raise RuntimeError(next(r["error"] for r in rows if r["error"]))
            if lot is passes[1][1]:
                rows0 = rows
            elif rows0 is not None and rows != rows0:
                raise RuntimeError("the second pass's rows differ from the first's")
            for label in table:
                table[label].append(cpu.get(label, 0.0) / len(lot) * 1e3)
    print(f"CPU ms a serial by stage ({serials} serials x {len(POINTS)} captures, one process, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}; {refit.__file__})")
    print(f"{'':<34}" + "".join(f"{name:>16}" for name, _ in passes))
    for label, vals in [("whole refit", totals), *table.items()]:
        print(f"{label:<34}" + "".join(f"{v:>16.1f}" for v in vals))


# ------------------------------------------------------------------------------------------
# the parent: the lot, the rounds, the table


def run_child(name: str, lot: Path, warm: Path, baseline: Path | None) -> dict[str, Any]:
    env = dict(os.environ)
    if baseline is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(baseline), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    with tempfile.NamedTemporaryFile(suffix=".json") as f:
        subprocess.run([sys.executable, str(HERE), "--child", name, "--lot", str(lot), "--warm", str(warm),
                        "--out", f.name], check=True, env=env, cwd=baseline or HERE.parent.parent)
        return json.loads(Path(f.name).read_text())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--serials", type=int, default=400)
    ap.add_argument("--rounds", type=int, default=2, help="the alternatives run in turn, this many times")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="a checkout of older code (e.g. a git worktree of main): its loop and 2-worker cluster too")
    ap.add_argument("--stages", action="store_true", help="CPU a serial by stage, in this process (first and second pass)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--lot", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--warm", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.child, a.lot, a.warm, a.out)
        return
    if a.stages:
        stages(a.serials)
        return

    runs: list[tuple[str, str, Path | None]] = [
        ("read+decode (read_capture)", "read_capture", None),
        ("read+decode (asammdf)", "asammdf", None),
        ("loop (1 process)", "loop", None),
        (f"threads (1 process, {THREADS})", "threads", None),
        ("dask, 1 worker", "dask-1", None),
        ("dask, 2 workers", "dask-2", None),
    ]
    if a.baseline is not None:
        base = a.baseline.resolve()
        runs += [("baseline loop (1 process)", "loop", base), ("baseline dask, 2 workers", "dask-2", base)]
    wall = {name: 0.0 for name, _, _ in runs}
    cpu, sys_cpu, switches = dict(wall), dict(wall), dict(wall)
    load0 = os.getloadavg()
    ref: list[dict[str, Any]] | None = None
    phase_diff = worst = 0.0
    with tempfile.TemporaryDirectory() as d:
        from eol_cal.lot.refit import REFIT_BATCH, REFIT_THREADS

        (Path(d) / "lot").mkdir()
        (Path(d) / "warm").mkdir()
        make_lot(Path(d) / "lot", a.serials)
        make_lot(Path(d) / "warm", REFIT_BATCH, first=a.serials)
        for r in range(a.rounds):
            for name, kind, baseline in runs:
                res = run_child(kind, Path(d) / "lot", Path(d) / "warm", baseline)
                wall[name] += res["wall"]
                cpu[name] += res["cpu"][0]
                sys_cpu[name] += res["cpu"][1]
                switches[name] += res["cpu"][2]
                if res["rows"]:
                    ref = ref or res["rows"]
                    for x, y in zip(ref, res["rows"], strict=True):
                        rel = max(abs(x[k] - y[k]) / max(abs(x[k]), abs(y[k]), 1e-300) for k in FIGURES)
                        if x["serial"] != y["serial"] or rel > SAME_REL:
                            raise RuntimeError(f"{name}: {y['serial']} differs from the first refit: {x} {y}")
                        worst = max(worst, rel)
                        phase_diff = max(phase_diff, abs(x["phase_k6"] - y["phase_k6"]))
                print(f"round {r + 1}: {name:<28} {a.serials / res['wall']:7.2f} serials/s  "
                      f"{res['cpu'][0] / a.serials * 1e3:6.1f} ms CPU/serial  load {os.getloadavg()[0]:.2f}", flush=True)
    n = a.serials * a.rounds
    print(f"{a.serials} serials x {len(POINTS)} captures x {a.rounds} round(s), {os.cpu_count()} cores, "
          f"load average {load0[0]:.2f} at the start, {os.getloadavg()[0]:.2f} at the end")
    base_name = "baseline loop (1 process)" if a.baseline is not None else "loop (1 process)"
    print(f"{'':<30}{'s':>8}{'serials/s':>11}{'vs ' + ('baseline' if a.baseline else 'loop'):>13}{'cpu/serial':>12}"
          f"{'cores':>7}{'sys/serial':>12}{'switches/serial':>17}")
    for name, _, _ in runs:
        print(f"{name:<30}{wall[name]:>8.1f}{n / wall[name]:>11.2f}{wall[base_name] / wall[name]:>12.2f}x"
              f"{cpu[name] / n * 1e3:>9.1f} ms{cpu[name] / wall[name]:>7.2f}{sys_cpu[name] / n * 1e3:>9.1f} ms"
              f"{switches[name] / n:>17.0f}")
    read = wall["read+decode (read_capture)"]
    threads = f"threads (1 process, {THREADS})"
    for name in ("loop (1 process)", threads):
        one = wall[name]
        print(f"{name}: {n / one:.1f} serials/s (target >= 40), {one / read:.2f}x the time to read and decode the "
              f"files (target <= 3x; {one / wall['read+decode (asammdf)']:.2f}x plain asammdf's)")
    # the one-process figure is what refit_in_process does by default: one thread is the loop's row
    default = {1: "loop (1 process)", THREADS: threads}.get(REFIT_THREADS)
    print(f"one process (refit_in_process's default, {REFIT_THREADS} thread(s)): "
          + (f"{n / wall[default]:.1f} serials/s (the {default} row)" if default else "not measured"))
    print(f"dask 2 workers: {wall['dask, 1 worker'] / wall['dask, 2 workers']:.2f}x 1 worker (target >= 1.8x), "
          f"{wall['loop (1 process)'] / wall['dask, 2 workers']:.2f}x the loop, "
          f"{wall[threads] / wall['dask, 2 workers']:.2f}x the threads")
    if a.baseline is not None:
        for new, old in (("loop (1 process)", "baseline loop (1 process)"),
                         (threads, "baseline loop (1 process)"),
                         ("dask, 2 workers", "baseline dask, 2 workers")):
            print(f"{new}: {wall[old] / wall[new]:.2f}x the baseline's")
    print(f"k6, c6, R^2, RMS within {worst:.2g} relative in every refit (at most {SAME_REL:g}); largest phase_k6 "
          f"difference {phase_diff:.3g} rad")


if __name__ == "__main__":
    main()
